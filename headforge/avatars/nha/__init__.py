"""Neural Head Avatars (Grassal et al. 2022) on headforge."""
