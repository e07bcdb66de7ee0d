"""A torch Dataset over a scan collection that opens the HDF5 file lazily in each DataLoader worker."""
import os

import numpy as np
import torch
from torch.utils.data import Dataset

from .collection import ScanCollection


class ScanDataset(Dataset):
    """Scans of a collection as dicts of tensors, optionally filtered by split / label.

    Item ``k`` is ``{"points": (N, 3) float32, "normals": (N, 3) float32, "index": () int64}`` where ``index`` is the
    scan's index in the collection (not ``k``). Scans have different N: batch with ``batch_size=1`` or a collate_fn
    that pads.

    The HDF5 handle is opened on first use in each process and never pickled: h5py handles must not cross a fork,
    so DataLoader workers each open their own.

    Parameters
    ----------
    path : str or Path
    split, label : str or collection of str, optional
        Filters, as in :meth:`ScanCollection.select`.
    """

    def __init__(self, path, split=None, label=None):
        self.path = str(path)
        with ScanCollection(self.path) as c:  # validates the file now, in the parent, with clear errors
            self.indices = np.asarray(c.select(split=split, label=label), dtype=np.int64)
        self._collection = None
        self._pid = None

    def _open(self):
        if self._collection is None or self._pid != os.getpid():
            self._collection = ScanCollection(self.path)
            self._pid = os.getpid()
        return self._collection

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, k):
        i = int(self.indices[k])
        scan = self._open()[i]
        return {"points": torch.from_numpy(scan.points), "normals": torch.from_numpy(scan.normals),
                "index": torch.tensor(i, dtype=torch.int64)}

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_collection"], state["_pid"] = None, None
        return state
