"""Data: video and frame-folder decoding, preprocessing (landmarks, masks, crops), the dataset
format (read and written here), and the synthetic benchmark subjects of ``headforge synth``."""
