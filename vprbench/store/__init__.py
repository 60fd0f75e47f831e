"""HDF5 descriptor stores keyed by method and image fingerprints (see `folder`, `rows_file` and `reader`)."""
from .folder import NO_FIT, StoreFolder, method_fingerprint, run_store, shard_range
from .reader import DescriptorStore
from .rows_file import DTYPES, DamagedRows, RowsIdentity, RowWriter, create_rows_file, inspect_rows_file

__all__ = ["DTYPES", "NO_FIT", "DamagedRows", "DescriptorStore", "RowWriter", "RowsIdentity", "StoreFolder", "create_rows_file",
           "inspect_rows_file", "method_fingerprint", "run_store", "shard_range"]
