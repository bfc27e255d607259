"""Camera model: geometry of a rotating camera, intrinsics and the radial distortion models."""
