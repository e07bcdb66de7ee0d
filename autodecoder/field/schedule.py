"""The learning-rate schedule every optimisation in the toolkit uses: a cosine decay to a floor."""
import math


def cosine_decay(step, total, final_fraction):
    """Factor of the peak learning rate at ``step`` of ``total``: 1 at step 0, ``final_fraction`` at ``total``.

    Half a cosine period from 1 down to ``final_fraction`` (held there after ``total``). A floor above 0 keeps the
    last steps moving: Adam at a vanishing rate would freeze the weights before the run ends.

    Parameters
    ----------
    step : int
        Steps taken so far (>= 0).
    total : int
        Steps of the whole run (the decay's length); 0 is treated as 1.
    final_fraction : float
        Factor at the end, in [0, 1].

    Returns
    -------
    float
    """
    return final_fraction + (1 - final_fraction) * 0.5 * (1 + math.cos(math.pi * min(step / max(total, 1), 1.0)))
