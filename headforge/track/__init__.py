"""Head tracking: fitting the parametric head model to the landmarks of a video (optionally
refined photometrically against the crops), and the ``headforge track`` pipeline."""
