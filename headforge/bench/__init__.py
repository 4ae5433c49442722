"""The synthetic benchmark (``headforge synth``): talking-head subjects with exact ground truth."""
