"""The latent model: one pair of networks over a collection of scans, each scan a code z (DeepSDF's autodecoder).

Training over an HDF5 collection with a latent table (``train``: ``train_latent``, ``train_collection``), in
modules of one job each: the run's settings and defaults (``options``), processes and threads (``distributed``), the
loop (``loop``), the training scans of a collection (``collection_split``), a run's checkpoints (``checkpoint``), its
log and loss plot (``history``); the checkpoint format and the trained model (``model``), the per-scan target pools
training draws from (``pools``) and the projection of a new scan onto a code with the networks frozen, optionally
fine-tuned (``projection``).

May import: ``autodecoder.field``, ``datasets``. Never ``autodecoder.scanning`` or ``inspection``.
"""
