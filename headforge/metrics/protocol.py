"""The one scoring protocol of every avatar method on held-out frames.

Where to score comes from the *tracked head model* and the frame's foreground mask, never from
a method's own template (a point avatar has no neck cut), and follows the head's pose:

- **head region** (:func:`scoring_regions`): the pixels above the neck cut -- the side of the
  cut's plane (fitted through the head model's neck-cut ring, oriented toward the head) that
  the head is on, taken at the ring's depth -- together with every pixel the tracked head model
  covers above its cut (dilated by ``margin`` of the image size for tracking error). When the
  head looks down, the cut's plane passes behind the chin: the pixels the chin covers still
  count.
- **face region**: the tracked head model's face region, inside the foreground mask.

Scores per frame (:func:`score_frames`), both images composited on white with the frame cut
to its mask inside the head region (the avatar has no shoulders):

- the papers' full-image PSNR / SSIM / L1 (PointAvatar, NHA), MS-SSIM (images over 160 px) and
  the avatar's CPBD sharpness (NHA Table 2);
- PSNR over head pixels only (the frame's or the avatar's, inside the head region) and over the
  face: a white background around a small head lifts the full-image PSNR by several dB;
- expression agreement: MediaPipe's 478 landmarks detected on the avatar and on the frame at the
  evaluation resolution, their mean distance (AKD, px) and the errors of the eye opening
  (upper-to-lower lid distance, mean of the six lid pairs) and mouth opening (inner lips), px.
  A frame where either detection fails counts in ``landmark_frames`` as missing.

Images (B, H, W, 3) float in [0, 1]; cameras OpenCV (:class:`headforge.render.camera.Cameras`).
"""

from __future__ import annotations

import numpy as np
import torch

from headforge.head.landmarks import EYELID_PAIRS
from headforge.render import mesh
from headforge.render.camera import Cameras

MOUTH_PAIRS = np.array([[13, 14], [82, 87], [312, 317]])  # MediaPipe inner-lip pairs: the mouth opening
MS_SSIM_MIN_SIZE = 161  # 5 scales of an 11-px window need images over 160 px


def matte_on_white(image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) frames composited on white by their soft ``mask`` (B, H, W)."""
    return image * mask[..., None] + (1 - mask[..., None])


@torch.no_grad()
def scoring_regions(vertices: torch.Tensor, faces: torch.Tensor, ring: torch.Tensor, face_vertices: torch.Tensor,
                    above_cut_faces: torch.Tensor, cameras: Cameras, margin: float = 0.02) -> tuple[torch.Tensor, torch.Tensor]:
    """(head region, face region), each (B, H, W) bool, of the tracked head model ``vertices``
    (B, V, 3, world = the dataset's camera frame) seen by ``cameras``. ``ring``: vertex ids of
    the neck cut; ``face_vertices``: (V,) bool; ``above_cut_faces``: (F,) bool, the faces above
    the cut. The face region is the model's face coverage (not yet cut to the mask)."""
    B, H, W = cameras.batch_size, cameras.height, cameras.width
    cam = cameras.world_to_camera(vertices)
    frags = mesh.rasterize(cameras, vertices, faces)
    fid = frags.face_id.clamp(min=0)
    hit = frags.face_id >= 0
    covered = hit & above_cut_faces[fid]
    face_faces = face_vertices[faces].all(1)
    face = hit & face_faces[fid]
    # the cut's plane: least-squares through the ring, normal toward the head's centroid
    pts = cam[:, ring]
    centre = pts.mean(1, keepdim=True)
    normal = torch.linalg.svd(pts - centre).Vh[:, -1]  # (B, 3)
    up = cam.mean(1) - centre[:, 0]
    normal = normal * torch.sign((normal * up).sum(-1, keepdim=True))
    # every pixel's ray point at the ring's depth, on the head's side of the plane?
    ys, xs = torch.meshgrid(torch.arange(H, dtype=cam.dtype), torch.arange(W, dtype=cam.dtype), indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)  # (HW, 3)
    rays = pix @ torch.linalg.inv(cameras.K.to(cam.dtype)).transpose(1, 2)  # (B, HW, 3), z = 1
    points = rays * centre[:, :, 2:3]
    above = (((points - centre) * normal[:, None]).sum(-1) > 0).reshape(B, H, W)
    radius = max(1, round(margin * max(H, W)))
    grown = torch.nn.functional.max_pool2d(covered.float()[:, None], 2 * radius + 1, stride=1, padding=radius)[:, 0] > 0
    return above | grown, face


def image_landmarks(images: torch.Tensor) -> np.ndarray:
    """(B, 478, 2) MediaPipe landmarks of (B, H, W, 3) images, NaN where no face is found."""
    from headforge.head.landmarks import detect_mediapipe

    out = np.full((len(images), 478, 2), np.nan)
    for b, image in enumerate(images.clamp(0, 1).cpu().numpy()):
        found = detect_mediapipe(image)
        if found is not None:
            out[b] = found
    return out


def _openings(landmarks: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(B,) mean distance (px) between the landmarks of each pair."""
    return np.linalg.norm(landmarks[:, pairs[:, 0]] - landmarks[:, pairs[:, 1]], axis=-1).mean(-1)


def landmark_regions() -> dict[str, np.ndarray]:
    """MediaPipe's 478 landmark indices by face region (eyes, irises, brows, lips, nose, oval;
    "rest" every other one): a partition of range(478)."""
    from mediapipe.python.solutions import face_mesh_connections as c

    def ids(*sets) -> set[int]:
        return {i for s in sets for edge in s for i in edge}

    out = {"eyes": ids(c.FACEMESH_LEFT_EYE, c.FACEMESH_RIGHT_EYE), "irises": set(range(468, 478)),
           "brows": ids(c.FACEMESH_LEFT_EYEBROW, c.FACEMESH_RIGHT_EYEBROW), "lips": ids(c.FACEMESH_LIPS),
           "nose": ids(c.FACEMESH_NOSE), "oval": ids(c.FACEMESH_FACE_OVAL)}
    out["rest"] = set(range(478)) - set().union(*out.values())
    return {k: np.array(sorted(v)) for k, v in out.items()}


def landmark_scores(pred: np.ndarray, truth: np.ndarray, by_region: bool = False) -> dict[str, np.ndarray]:
    """Per-frame (B,) scores of MediaPipe landmarks ``pred`` on the avatar's images against
    ``truth`` on the frames ((B, 478, 2) px, NaN where no face was found): AKD over all 478, the
    eye- and mouth-opening errors, and with ``by_region`` AKD per :func:`landmark_regions` region
    (``akd_<region>_px``), the openings themselves (``<eye|mouth>_opening_<avatar|frame>_px``:
    an error's sign, e.g. a mouth drawn closed), and the split of AKD into the frame's mean
    displacement (``landmark_shift_px``: its length, the whole face drawn off by a shift) and what
    is left with it removed (``akd_unshifted_px``)."""
    dist = np.linalg.norm(pred - truth, axis=-1)  # (B, 478)
    eyes, mouths = (_openings(pred, EYELID_PAIRS), _openings(truth, EYELID_PAIRS)), \
        (_openings(pred, MOUTH_PAIRS), _openings(truth, MOUTH_PAIRS))
    out = {"akd_px": dist.mean(-1),
           "eye_opening_error_px": np.abs(eyes[0] - eyes[1]),
           "mouth_opening_error_px": np.abs(mouths[0] - mouths[1])}
    if by_region:
        out |= {f"akd_{name}_px": dist[:, idx].mean(-1) for name, idx in landmark_regions().items()}
        out |= {"eye_opening_avatar_px": eyes[0], "eye_opening_frame_px": eyes[1],
                "mouth_opening_avatar_px": mouths[0], "mouth_opening_frame_px": mouths[1]}
        shift = (pred - truth).mean(1, keepdims=True)  # (B, 1, 2)
        out |= {"landmark_shift_px": np.linalg.norm(shift[:, 0], axis=-1),
                "akd_unshifted_px": np.linalg.norm(pred - shift - truth, axis=-1).mean(-1)}
    return out


def _masked_psnr(pred: torch.Tensor, gt: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """(B,) PSNR over ``pixels`` (B, H, W) bool; NaN where a frame has none."""
    err = ((pred - gt) ** 2).mean(-1)
    n = pixels.flatten(1).sum(1)
    mse = (err * pixels).flatten(1).sum(1) / n.clamp(min=1)
    return torch.where(n > 0, -10 * torch.log10(mse.clamp(min=1e-10)), torch.full_like(mse, float("nan")))


@torch.no_grad()
def composite(rgb: torch.Tensor, image: torch.Tensor, mask: torch.Tensor, region: torch.Tensor):
    """(avatar, frame) as scored: the avatar's render (on white) inside ``region``, the frame cut
    to ``mask`` inside ``region``, both on white."""
    area = region[..., None].to(rgb.dtype)
    return rgb * area + (1 - area), matte_on_white(image, mask * region)


@torch.no_grad()
def score_frames(rgb: torch.Tensor, coverage: torch.Tensor, image: torch.Tensor, mask: torch.Tensor,
                 region: torch.Tensor, face: torch.Tensor, landmarks: bool = True,
                 by_region: bool = False) -> dict[str, np.ndarray]:
    """Per-frame scores (name -> (B,) float64, NaN where undefined) of the avatar's ``rgb``
    (B, H, W, 3, on white) and ``coverage`` (B, H, W) against the frames ``image`` / ``mask``,
    inside the head ``region`` and the model's ``face`` region ((B, H, W) bool each)."""
    from headforge.metrics.image import cpbd, l1, ms_ssim, psnr, ssim

    pred, gt = composite(rgb, image, mask, region)
    head = region & ((mask > 0.5) | (coverage > 0.5))
    B = len(rgb)
    out = {"psnr": np.array([psnr(pred[b:b + 1], gt[b:b + 1]).item() for b in range(B)]),
           "ssim": np.array([ssim(pred[b:b + 1], gt[b:b + 1]).item() for b in range(B)]),
           "l1": np.array([l1(pred[b:b + 1], gt[b:b + 1]).item() for b in range(B)]),
           "psnr_head": _masked_psnr(pred, gt, head).double().cpu().numpy(),
           "psnr_face": _masked_psnr(pred, gt, face & (mask > 0.5)).double().cpu().numpy()}
    if min(rgb.shape[1:3]) >= MS_SSIM_MIN_SIZE:
        out["ms_ssim"] = np.array([ms_ssim(pred[b:b + 1], gt[b:b + 1]).item() for b in range(B)])
    out["cpbd"] = np.array([cpbd(pred[b].cpu().numpy()) for b in range(B)])
    if landmarks:
        out |= landmark_scores(image_landmarks(pred), image_landmarks(gt), by_region)
    return out


def summarise(scores: dict[str, np.ndarray]) -> dict:
    """Means over frames (NaN-aware; "n/a" when no frame has the score), plus the number of
    frames and, with landmark scores, of frames where both detections succeeded."""
    out = {}
    for name, values in scores.items():
        finite = values[np.isfinite(values)]
        out[name] = round(float(finite.mean()), 4) if len(finite) else "n/a"
    n = len(next(iter(scores.values()))) if scores else 0
    out["frames"] = n
    if "akd_px" in scores:
        out["landmark_frames"] = int(np.isfinite(scores["akd_px"]).sum())
    return out


class TrackedHead:
    """A dataset's tracked head model, posed at frame parameters: the source of the scoring
    regions. ``data``: the head model's HeadModelData; ``shape`` (1, S) the tracked identity."""

    def __init__(self, data, shape: torch.Tensor):
        from headforge.head.model import HeadModel
        from headforge.head.topology import faces_above_neck_cut, neck_cut_ring

        self.model = HeadModel(data)
        self.shape = shape.float()[:, : self.model.n_shape]
        self.ring = torch.as_tensor(neck_cut_ring(data), dtype=torch.long)
        self.above_cut = torch.as_tensor(faces_above_neck_cut(data))
        face = torch.zeros(self.model.num_vertices, dtype=torch.bool)
        if "face" in self.model.region_names:
            face[self.model.region("face")] = True
        self.face_vertices = face

    @torch.no_grad()
    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, V, 3) camera-space vertices at ``params`` (FRAME_KEYS, tracked poses)."""
        from headforge.head.pose import FRAME_KEYS, head_to_camera

        B = params["translation"].shape[0]
        out = self.model(shape=self.shape.expand(B, -1), **{k: params[k].float() for k in FRAME_KEYS if k != "translation"})
        return head_to_camera(out.vertices, params["translation"].float())

    def regions(self, params: dict[str, torch.Tensor], cameras: Cameras, chunk: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
        """(head region, face region), (B, H, W) bool on ``cameras``' device, of the frames
        ``params`` seen by ``cameras`` (computed on the CPU, where the tracked model lives)."""
        from headforge.head.pose import select

        device = cameras.K.device
        cameras = cameras.to("cpu")
        params = {k: v.cpu() for k, v in params.items()}
        heads, faces = [], []
        B = params["translation"].shape[0]
        for start in range(0, B, chunk):
            rows = slice(start, min(start + chunk, B))
            cams = Cameras(cameras.K[rows], cameras.R[rows], cameras.t[rows], cameras.width, cameras.height)
            h, f = scoring_regions(self.vertices(select(params, rows)), self.model.faces, self.ring,
                                   self.face_vertices, self.above_cut, cams)
            heads.append(h)
            faces.append(f)
        return torch.cat(heads).to(device), torch.cat(faces).to(device)
