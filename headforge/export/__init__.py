"""Standard file formats for avatars: animatable glTF 2.0 (:mod:`headforge.export.gltf`)."""
