"""Image front end: features, robust homographies, the keyframe tracker, stills and encoder interpolation."""
