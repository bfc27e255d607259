"""Radial distortion (section 7): estimation from matches and the per-keyframe correction."""
