"""vprbench: the benchmark suite for visual place recognition."""
__version__ = "0.1.0"

from .errors import VPRBenchError
from .methods import Method, available_methods, create_method, register_method

__all__ = ["__version__", "Method", "VPRBenchError", "available_methods", "create_method", "register_method"]
