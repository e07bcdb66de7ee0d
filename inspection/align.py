"""When inspection registers scans: ``align='auto'`` decided from how far the good training scans' poses spread
(:func:`datasets.registration.pose_spread`).

The registration itself (coarse-to-fine robust ICP with a placement prior, group registration of the training
scans) and the decision are :mod:`datasets.registration`'s, imported here under the names inspection has always
used.
"""
from datasets.registration import (  # noqa: F401 (inspection's names for the registration)
    ALIGN_SCANS, AUTO_RATIO, AUTO_SCANS, DEFAULT_LEVELS, GROUP_ROUNDS, GROUP_SETTLED, HUBER, MAX_SOURCE, PRIOR_DEGREES,
    PRIOR_SIZE, START_DEGREES, START_ITERATIONS, Aligner, _starts, moved_by, pose_spread, register_group)

