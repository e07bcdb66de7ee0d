"""Scans as data: HDF5 scan collections, scanner-file import, virtual scanning and defect synthesis."""
from .cloud_io import read_cloud, write_cloud
from .collection import ScanCollection
from .frame import Frame
from .scan import Scan
from .validation import ScanReadError

__all__ = ["Scan", "ScanCollection", "ScanDataset", "ScanReadError", "Frame", "read_cloud", "write_cloud"]


def __getattr__(name):
    # ScanDataset needs torch (seconds to import); load it only when asked for, so `import datasets` stays light
    if name == "ScanDataset":
        from .scan_dataset import ScanDataset

        return ScanDataset
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
