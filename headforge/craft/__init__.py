"""HeadCraft (seed 002): scans in, registered template with free displacements out, baked into
UV displacement maps.

- :mod:`headforge.craft.scans` -- generated scan sets with exact ground truth; external scan reader;
- :mod:`headforge.craft.register` -- landmark fit, consistent subdivision, two-stage displacements;
- :mod:`headforge.craft.uvmap` -- the face/scalp UV layout, baking, seam post-processing, lookup.

Coordinates: metres, y up, face toward +z (headforge's canonical head space).
"""
