"""Camera models and calibration targets: pinhole intrinsics with OpenCV distortion,
world-to-camera poses, similarities between frames, projection and undistortion
(``model``), and the printed ChArUco or checkerboard board (``board``)."""
