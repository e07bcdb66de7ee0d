"""Scans as data: HDF5 scan collections, scanner-file import, virtual scanning and defect synthesis."""
