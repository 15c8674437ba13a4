"""Geometry from posed photos: the visual hull (``visual_hull``), a turntable's
circular motion and the placement of photos on it (``turntable``,
``turntable_placement``), the world frame (``world_frame``: board, turntable axis,
ground plane), pose checks against silhouettes (``pose_check``), and the UV
atlas's rasterisation (``atlas``)."""
