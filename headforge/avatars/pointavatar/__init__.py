"""PointAvatar (Zheng et al., CVPR 2023) on the avatar platform: docs/pointavatar.md."""
