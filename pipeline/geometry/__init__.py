"""Geometry from posed photos: the visual hull, the turntable's circular motion,
the world frame (board, turntable axis, ground plane), pose checks against
silhouettes, and the UV atlas's rasterisation."""
