"""The browser viewer (``headforge view``): a three.js page served from memory on 127.0.0.1,
showing an avatar, a tracked dataset or a HeadCraft map (:mod:`.scene`, :mod:`.server`)."""
