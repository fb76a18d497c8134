"""The SLAM loop: initialisation, tracking, mapping with bundle adjustment, keyframes, outputs, resume."""
