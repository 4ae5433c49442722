"""Data: video and frame-folder decoding, preprocessing (landmarks, masks, crops) and the
dataset format (read and written here; ``headforge synth``'s subjects are in headforge.bench)."""
