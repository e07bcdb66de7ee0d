"""Scanning with a stochastic field: what a sensor would see, and where to look next.

Correlated ray casting through the field (``rays``), the evidence of a scan's own rays about free space
(``free_space``: did the sensor see through where the field puts material?; where good parts have a surface, the
only samples it may accuse, ``surface_band``; the surface a scan saw from its points alone, its rims and the rays
that pass through it, ``own_surface``), next-best-view planning (``views``) and fine-tuning a fitted field on newly scanned points
(``update``).

May import: ``autodecoder.field``, ``autodecoder.latent``, ``datasets``. Never ``inspection``.
"""
