"""HDF5 descriptor stores keyed by method and image fingerprints (see `folder` and `rows`)."""
from .folder import NO_FIT, StoreFolder, method_fingerprint, run_store, shard_range
from .rows_file import DTYPES, DescriptorStore, RowsIdentity, RowWriter, create_rows_file, inspect_rows_file

__all__ = ["DTYPES", "NO_FIT", "DescriptorStore", "RowWriter", "RowsIdentity", "StoreFolder", "create_rows_file",
           "inspect_rows_file", "method_fingerprint", "run_store", "shard_range"]
