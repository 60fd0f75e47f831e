"""Core methods: importing this module registers them."""
from . import anyloc

anyloc.register()
