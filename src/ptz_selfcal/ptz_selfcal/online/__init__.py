"""The online calibrator: bounded keyframe set, keyframe solver, gates, status, the session."""
