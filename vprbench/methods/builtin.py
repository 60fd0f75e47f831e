"""Core methods: importing this module registers them."""
