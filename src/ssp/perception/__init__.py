"""Perception front end: from a depth image or cloud to segments and pose hypotheses.

Geometry (table plane, normals, segmentation, depth back-projection) lives in the submodules
:mod:`ssp.perception.table`, :mod:`ssp.perception.normals`, :mod:`ssp.perception.segmentation`
and :mod:`ssp.perception.depth`.
"""
