"""Training batches of one oriented cloud: GP posterior targets at sampled points, in the model frame."""
import numpy as np
from scipy.spatial import cKDTree

from autodecoder.field.gp_targets import GPPosterior
from autodecoder.field.sampling import Box, sample_mean_targets, sample_pair_clusters

DEFAULT_LENGTHSCALE_FACTOR = 2.0
# fit_cloud's own default (one dense cloud): a sharper posterior mean that its 4000 Adam steps can still follow; the
# lowest surface error of the factors tried (docs/results.md#single-cloud-fit-defaults-fandisk). Latent training over
# many partial scans keeps DEFAULT_LENGTHSCALE_FACTOR (its inspection figures were measured with it).
FIT_LENGTHSCALE_FACTOR = 1.5
MIN_LENGTHSCALE = 0.004  # in the unit-cube frame: finer than a SIREN of the default size can resolve anyway


def point_spacing(points, k=8):
    """Typical distance between neighbouring samples of a surface point cloud.

    Each point's local area per sample is estimated as pi d_k^2 / k (d_k: distance to its k-th neighbour); the
    spacing is the square root of the median area. Independent of the cloud's extent and of the units.

    Parameters
    ----------
    points : (n, 3) array

    Returns
    -------
    float
    """
    k = min(k, len(points) - 1)
    if k < 1:
        raise ValueError("at least two points are needed to measure their spacing")
    dist, _ = cKDTree(points).query(points, k + 1)
    return float(np.sqrt(np.median(np.pi * dist[:, -1] ** 2 / k)))


def default_lengthscale(points, factor=DEFAULT_LENGTHSCALE_FACTOR):
    """Kernel lengthscale from the data's own sampling density: ``factor`` x the point spacing (model frame).

    With h = 2 x spacing, about 4h x 4h / spacing^2 = 64 samples fall into the kernel's support on a surface,
    enough for a smooth posterior mean, while features of a few h stay crisp.
    """
    return max(factor * point_spacing(points), MIN_LENGTHSCALE)


def default_box(points, lengthscale):
    """The integration box: the points' bounding cube grown by 10% of unit size or two kernel supports."""
    return Box.around(points, margin=max(0.1, 4 * lengthscale))


class CloudTargets:
    """GP posterior targets of one cloud (model frame) and the batches that train on them.

    Parameters
    ----------
    points, normals : (n, 3) arrays
        The oriented cloud in the model frame.
    lengthscale : float
        Kernel lengthscale h (model frame).
    box : Box, optional
        Integration domain B (default :func:`default_box`).
    normal_noise, amplitude : float
        See :class:`GPPosterior`.
    """

    def __init__(self, points, normals, lengthscale, box=None, normal_noise=0.0, amplitude=1.0):
        self.posterior = GPPosterior(points, normals, lengthscale, normal_noise=normal_noise, amplitude=amplitude)
        self.box = box if box is not None else default_box(points, lengthscale)
        self.points32 = np.ascontiguousarray(points, dtype=np.float32)
        self._outside_values = {}  # outside_value's results, by its arguments

    @property
    def lengthscale(self):
        return self.posterior.lengthscale

    def outside_value(self, n_lines=256, n_steps=41, seed=0):
        """Half the jump of the posterior mean's potential across the surface: the value g takes outside a closed
        surface whose mean surface is at g = 0 (and -value inside).

        Integrates mu . n along the normal line through up to ``n_lines`` cloud points, over the kernel's reach
        on both sides (t in [-2r, 2r], r the support radius), by the trapezoid rule; returns half the median.
        Cached per set of arguments (the boundary term asks for it at every step).

        Returns
        -------
        float (model frame)
        """
        key = (int(n_lines), int(n_steps), int(seed))
        if key not in self._outside_values:
            rng = np.random.default_rng(seed)
            post = self.posterior
            pick = rng.choice(len(post.points), min(n_lines, len(post.points)), replace=False)
            p, n = post.points[pick], post.normals[pick]
            t = np.linspace(-2 * post.radius, 2 * post.radius, n_steps)
            x = (p[:, None, :] + t[None, :, None] * n[:, None, :]).reshape(-1, 3)
            along = np.einsum("ijk,ik->ij", post.mean(x).reshape(len(p), n_steps, 3), n)
            self._outside_values[key] = float(0.5 * np.median(np.trapezoid(along, t, axis=1)))
        return self._outside_values[key]

    def boundary_batch(self, n, rng):
        """n points uniform on the surface of the integration box -> (n, 3) float32."""
        return self.box.surface(n, rng).astype(np.float32)

    def mean_batch(self, n, rng, near_fraction=0.5):
        """x (n, 3), mu (n, 3), omega (n,) float32: see :func:`sample_mean_targets`."""
        n_near = int(round(n * near_fraction))
        return sample_mean_targets(self.posterior, self.box, n - n_near, n_near, rng)

    def pair_batch(self, n_clusters, cluster_size, rng):
        """x (m, 3), sigma (m, m), weights (m, m) float32 for the covariance loss: see
        :func:`sample_pair_clusters`. Clusters have half-width 2h so that their pairs cover Sigma's support."""
        x, weights = sample_pair_clusters(self.box, n_clusters, cluster_size, self.posterior.radius, rng)
        sigma = self.posterior.covariance_matrix(x).toarray().astype(np.float32)
        return x, sigma, weights

    def screen_batch(self, n, rng):
        """n cloud points (all of them, in random order, when the cloud is smaller) -> (min(n, N), 3) float32."""
        if n >= len(self.points32):
            return self.points32[rng.permutation(len(self.points32))]
        return self.points32[rng.choice(len(self.points32), n, replace=False)]


def cloud_frame_and_targets(points, normals, lengthscale=None, factor=FIT_LENGTHSCALE_FACTOR):
    """The frame and GP targets of one cloud, as every single-cloud fit builds them.

    Parameters
    ----------
    points, normals : (n, 3) float64 arrays
        A validated oriented cloud (:func:`datasets.validation.check_oriented_cloud`), its own (world) units.
    lengthscale : float, optional
        Kernel lengthscale in world units; default ``factor`` median point spacings (:func:`default_lengthscale`).
    factor : float

    Returns
    -------
    frame : datasets.frame.Frame
        World -> the unit-cube model frame of the cloud's bounding box.
    targets : CloudTargets
        In the model frame (lengthscale ``targets.lengthscale`` in model units).
    """
    from datasets.frame import Frame

    frame = Frame.fit(points)
    model_points = frame.to_collection(points)
    h = (default_lengthscale(model_points, factor) if lengthscale is None else float(lengthscale) * frame.scale)
    return frame, CloudTargets(model_points, normals, h)
