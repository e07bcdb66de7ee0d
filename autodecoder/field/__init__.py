"""The single-cloud stochastic field: NSSPR for one oriented point cloud.

The compact kernel and the Gaussian-process posterior it gives (``kernel``, ``gp_targets``), the sample boxes and
target draws (``sampling``, ``targets``), the SIREN layers and the mean / covariance networks built of them
(``siren``), the B-spline grid's (``grid_networks``), the choice between the two (``networks``), the paper's losses (``losses``), the fitted field and its statistical queries (``stochastic_field``),
the fit itself (``fit``), and the exact grid minimiser of the mean loss that the fit is measured against
(``grid_minimiser``). Everything here works on one cloud; the latent code is only an extra network input.

May import: numpy, scipy, torch, ``datasets``. Never ``autodecoder.latent``, ``autodecoder.scanning`` or
``inspection``.
"""
