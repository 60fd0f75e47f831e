"""vprbench: the benchmark suite for visual place recognition."""
__version__ = "0.3.0.dev0"  # after 0.2; records and bundles carry it

from .errors import VPRBenchError
from .methods import Method, available_methods, create_method, register_method

__all__ = ["__version__", "Method", "VPRBenchError", "available_methods", "create_method", "register_method"]
