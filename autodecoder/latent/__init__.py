"""The latent model: one pair of networks over a collection of scans, each scan a code z (DeepSDF's autodecoder).

Training over an HDF5 collection with a latent table, checkpoints that resume (``train``), the checkpoint format and
the trained model (``model``), the per-scan target pools training draws from (``pools``) and the projection of a new
scan onto a code with the networks frozen, optionally fine-tuned (``projection``).

May import: ``autodecoder.field``, ``datasets``. Never ``autodecoder.scanning`` or ``inspection``.
"""
