"""Head tracking: fitting the parametric head model to landmarks of a video."""
