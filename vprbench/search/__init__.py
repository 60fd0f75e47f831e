"""Descriptor search: exact top-K search over row sources within a memory budget in bytes
(exact.py), approximate search with a faiss IVF-PQ or HNSW index re-scored exactly
(approximate.py), the checks on rows before they are searched (row_checks.py), and the fixed
grid of tiles the products are computed on (chunks.py)."""
