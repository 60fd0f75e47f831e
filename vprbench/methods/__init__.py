"""Methods: image -> global descriptor. See `Method` for the contract."""
from .base import Method, l2_normalise
from .registry import available_methods, create_method, method_entry, register_method

__all__ = ["Method", "l2_normalise", "available_methods", "create_method", "method_entry", "register_method"]
