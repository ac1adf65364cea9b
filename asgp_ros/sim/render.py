"""Fast RGB-D renderer of the textured room (:mod:`asgp_ros.sim.scene`) with sensor noise.

Rendering: every textured quad is clipped to the view frustum (Sutherland-Hodgman in the
camera frame), its texture (a mip level chosen for the quad's distance) is warped into the
quad's image bounding box with one homography (``cv2.warpPerspective``), and a z-buffer
keeps the nearest surface. Per pixel, the inverse depth of a plane is affine in (u, v):
with the plane n . X = d in the camera frame and the ray r = K^-1 (u, v, 1),
1/z = (n . r) / d, so depth costs three multiply-adds per pixel.

Depth sensor model (structured-light / stereo RGB-D camera such as the Kinect or a
RealSense, after Khoshelham & Elberink 2012, "Accuracy and resolution of Kinect depth
data", Sensors 12(2)):

* depth is measured as disparity delta = f b / z (focal f in pixels, baseline b), with
  Gaussian disparity noise of std ``disparity_sigma`` px, so the axial depth noise is
  sigma_z = z^2 / (f b) * sigma_delta (grows with z^2; 1.4 mm at 1 m, 3.5 cm at 5 m with
  the defaults), then quantised to 1/``subpixel`` px of disparity;
* range limits: no data closer than ``min_range`` or farther than ``max_range``;
* holes: at depth discontinuities (the projector shadow / mixed pixels), in random blobs
  (specular or absorbing patches) and single-pixel dropouts; a hole reads 0.

Colour: a slight optical blur and additive Gaussian image noise.

Noise fields (image and disparity) are drawn once per renderer and each frame uses a
randomly offset window of them, so consecutive frames get different (spatially shifted)
noise at a fraction of the cost of fresh Gaussian samples.

Coordinates: camera poses are optical-frame poses (z forward, x right, y down) in the
world; :class:`asgp_ros.vo.extrinsics.CameraExtrinsic` gives it from a chair pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from asgp_ros.sim.scene import Scene
from asgp_ros.vo.extrinsics import DEFAULT_EXTRINSIC, CameraExtrinsic, invert


def default_camera_matrix(width: int = 640, height: int = 480,
                          hfov_deg: float = 62.7) -> np.ndarray:
    """Pinhole K [3, 3] with square pixels; 62.7 deg horizontal FOV gives f = 525 at 640 px."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class DepthNoise:
    """RGB-D sensor imperfections (see the module docstring); ``perfect()`` turns them off."""

    min_range: float = 0.3
    max_range: float = 6.0
    baseline: float = 0.075
    disparity_sigma: float = 0.056
    subpixel: float = 8.0
    edge_fraction: float = 0.05
    blob_fraction: float = 0.02
    dropout_fraction: float = 0.005
    image_sigma: float = 2.0
    blur_sigma: float = 0.6

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(f"need 0 <= min_range < max_range, got {self.min_range}, "
                             f"{self.max_range}")
        for name in ("baseline", "disparity_sigma", "subpixel", "edge_fraction",
                     "blob_fraction", "dropout_fraction", "image_sigma", "blur_sigma"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0")

    @staticmethod
    def perfect(min_range: float = 0.0, max_range: float = 1e9) -> DepthNoise:
        return DepthNoise(min_range=min_range, max_range=max_range, disparity_sigma=0.0,
                          subpixel=0.0, edge_fraction=0.0, blob_fraction=0.0,
                          dropout_fraction=0.0, image_sigma=0.0, blur_sigma=0.0)


def _clip_polygon(poly: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: keep the part of the polygon [n, 3] with a.X + b >= 0 per plane.

    planes: [P, 4] rows (a_x, a_y, a_z, b). Returns [m, 3] (m = 0 when nothing is left).
    """
    for plane in planes:
        if len(poly) == 0:
            break
        s = poly @ plane[:3] + plane[3]
        if np.all(s >= 0.0):
            continue
        if np.all(s < 0.0):
            return poly[:0]
        out = []
        n = len(poly)
        for i in range(n):
            j = (i + 1) % n
            if s[i] >= 0.0:
                out.append(poly[i])
            if (s[i] >= 0.0) != (s[j] >= 0.0):
                t = s[i] / (s[i] - s[j])
                out.append(poly[i] + t * (poly[j] - poly[i]))
        poly = np.array(out)
    return poly


class RGBDRenderer:
    """Renders colour (BGR uint8) and depth (float32 metres, 0 = no data) images of a scene.

    Args:
        scene: the textured room.
        camera_matrix: K [3, 3]; default :func:`default_camera_matrix` for the size.
        width, height: image size in pixels.
        noise: the sensor model; ``DepthNoise.perfect()`` for exact images.
        extrinsic: camera mounting used by :meth:`render_chair`.
        seed: noise seed; frame k of a renderer is reproducible from (seed, k).
    """

    def __init__(self, scene: Scene, camera_matrix: np.ndarray | None = None,
                 width: int = 640, height: int = 480, noise: DepthNoise | None = None,
                 extrinsic: CameraExtrinsic = DEFAULT_EXTRINSIC, seed: int = 0) -> None:
        if width < 16 or height < 16:
            raise ValueError(f"image size {width}x{height} is too small")
        self.scene = scene
        self.width, self.height = int(width), int(height)
        K = default_camera_matrix(width, height) if camera_matrix is None else camera_matrix
        self.K = np.asarray(K, float).reshape(3, 3)
        self.noise = DepthNoise() if noise is None else noise
        self.extrinsic = extrinsic
        self.seed = int(seed)
        self.frame_index = 0
        self._normals = [q.normal for q in scene.quads]
        self._corners = [q.corners for q in scene.quads]
        # noise banks, a margin larger than the image: each frame takes a random window
        # (drawing ~1.2 M Gaussian samples per frame would cost more than the rendering)
        cv2.setRNGSeed(self.seed % (2**31 - 1) + 1)
        self._margin = 64
        hb, wb = self.height + self._margin, self.width + self._margin
        self._image_bank = np.empty((hb, wb, 3), np.int16)
        cv2.randn(self._image_bank, 0, self.noise.image_sigma)  # type: ignore[call-overload]
        self._disp_bank = np.empty((hb, wb), np.float32)
        cv2.randn(self._disp_bank, 0,  # type: ignore[call-overload]
                  self.noise.disparity_sigma)
        self._rng = np.random.default_rng(self.seed)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        self._u = np.arange(self.width, dtype=np.float32)[None, :]
        self._v = np.arange(self.height, dtype=np.float32)[:, None]
        # frustum planes a.X + b >= 0 in the camera frame (1 px margin around the image)
        xl, xr = (-0.5 - 1 - cx) / fx, (self.width - 0.5 + 1 - cx) / fx
        yt, yb = (-0.5 - 1 - cy) / fy, (self.height - 0.5 + 1 - cy) / fy
        self._planes = np.array([
            [0.0, 0.0, 1.0, -0.02],  # near plane z >= 2 cm
            [1.0, 0.0, -xl, 0.0],  # x >= xl z
            [-1.0, 0.0, xr, 0.0],  # x <= xr z
            [0.0, 1.0, -yt, 0.0],
            [0.0, -1.0, yb, 0.0],
        ])

    # ------------------------------------------------------------------------------------
    def render_chair(self, x: float, y: float, theta: float, noisy: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Render from the camera mounted on a chair at planar pose (x, y, theta)."""
        return self.render(self.extrinsic.camera_pose_planar(x, y, theta), noisy=noisy)

    def render(self, T_world_cam: np.ndarray, noisy: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
        """Render the scene seen from the optical-frame pose T_world_cam [4, 4].

        Returns:
            (image [h, w, 3] uint8 BGR, depth [h, w] float32 metres with 0 = no data).
            With ``noisy=False`` the exact image and z-buffer depth (inf where nothing).
        """
        T_cw = invert(np.asarray(T_world_cam, float))
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        K = self.K
        h, w = self.height, self.width
        image = np.zeros((h, w, 3), np.uint8)
        ibuf = np.zeros((h, w), np.float32)  # inverse depth, 0 = empty
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        cam_pos = T_world_cam[:3, 3]
        for q, n_w, corners in zip(self.scene.quads, self._normals, self._corners,
                                   strict=True):
            if np.dot(n_w, cam_pos - q.origin) <= 0.0:
                continue  # back face
            corners_c = corners @ R.T + t
            poly = _clip_polygon(corners_c, self._planes)
            if len(poly) < 3:
                continue
            px = poly[:, 0] / poly[:, 2] * fx + cx
            py = poly[:, 1] / poly[:, 2] * fy + cy
            x0 = max(0, math.floor(px.min()))
            y0 = max(0, math.floor(py.min()))
            x1 = min(w, math.ceil(px.max()) + 1)
            y1 = min(h, math.ceil(py.max()) + 1)
            if x1 - x0 < 1 or y1 - y0 < 1:
                continue
            # mip level: texels per image pixel at the typical distance of the visible part
            z_typ = math.sqrt(max(poly[:, 2].min(), 0.05) * poly[:, 2].max())
            img_ppm = fx / z_typ
            tex_ppm = q.texture.shape[1] / np.linalg.norm(q.u)
            level = int(np.clip(math.floor(math.log2(max(tex_ppm / (1.5 * img_ppm), 1.0))),
                                0, len(q.mips) - 1))
            tex = q.mips[level]
            th, tw = tex.shape[:2]
            # homography texel (s, t) -> pixel: K [R | t] [u/tw, v/th, origin'] (texel centres)
            M = np.column_stack([q.u / tw, q.v / th, q.origin + 0.5 * q.u / tw + 0.5 * q.v / th])
            Hm = K @ (R @ M + np.outer(t, [0.0, 0.0, 1.0]))
            S = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
            bw, bh = x1 - x0, y1 - y0
            patch = cv2.warpPerspective(tex, S @ Hm, (bw, bh), flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_REPLICATE)
            mask = np.zeros((bh, bw), np.uint8)
            pts = np.round(np.column_stack([px - x0, py - y0]) * 16).astype(np.int32)
            cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
            # inverse depth of the plane n.X = d (camera frame): 1/z = (n . K^-1 (u,v,1)) / d
            n_c = R @ n_w
            d = float(n_c @ (R @ q.origin + t))
            if abs(d) < 1e-9:
                continue
            a, b = n_c[0] / (fx * d), n_c[1] / (fy * d)
            c = (n_c[2] - n_c[0] * cx / fx - n_c[1] * cy / fy) / d
            iz = (self._u[:, x0:x1] * np.float32(a) + (self._v[y0:y1] * np.float32(b)
                                                      + np.float32(c)))
            roi = ibuf[y0:y1, x0:x1]
            closer = cv2.bitwise_and(cv2.compare(iz, roi, cv2.CMP_GT), mask)  # z-test
            cv2.copyTo(iz, closer, roi)  # writes into the views (ibuf, image) in place
            cv2.copyTo(patch, closer, image[y0:y1, x0:x1])
        self.frame_index += 1
        if not noisy:
            with np.errstate(divide="ignore"):
                depth = np.where(ibuf > 0, 1.0 / np.maximum(ibuf, 1e-12), np.inf)
            return image, depth.astype(np.float32)
        return self._apply_noise(image, ibuf)

    # ------------------------------------------------------------------------------------
    def _apply_noise(self, image: np.ndarray, ibuf: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        nz = self.noise
        cv2.setRNGSeed((self.seed * 1_000_003 + self.frame_index) % (2**31 - 1))
        h, w = ibuf.shape
        if nz.blur_sigma > 0:
            image = cv2.GaussianBlur(image, (0, 0), nz.blur_sigma)
        oy, ox = self._rng.integers(0, self._margin, 2)
        if nz.image_sigma > 0:
            noise = self._image_bank[oy:oy + h, ox:ox + w]
            image = cv2.add(image, noise, dtype=cv2.CV_8U)
        valid = ibuf > 0
        fb = float(self.K[0, 0] * nz.baseline)
        if nz.disparity_sigma > 0 or nz.subpixel > 0:
            # Khoshelham & Elberink 2012, eq. 7-8: disparity noise -> sigma_z ~ z^2
            disp: np.ndarray = ibuf * np.float32(fb)
            if nz.disparity_sigma > 0:
                oy, ox = self._rng.integers(0, self._margin, 2)
                disp += self._disp_bank[oy:oy + h, ox:ox + w]
            if nz.subpixel > 0:
                disp = np.round(disp * np.float32(nz.subpixel)) / np.float32(nz.subpixel)
            valid &= disp > 0
            with np.errstate(divide="ignore"):
                depth = np.float32(fb) / np.where(valid, disp, np.float32(1.0))
        else:
            with np.errstate(divide="ignore"):
                depth = 1.0 / np.where(valid, ibuf, np.float32(1.0))
        depth = depth.astype(np.float32)
        valid &= (depth >= nz.min_range) & (depth <= nz.max_range)
        if nz.edge_fraction > 0:
            zt = np.where(ibuf > 0, 1.0 / np.maximum(ibuf, 1e-6), 1e3).astype(np.float32)
            kernel = np.ones((3, 3), np.uint8)
            spread = cv2.dilate(zt, kernel) - cv2.erode(zt, kernel)
            valid &= spread <= nz.edge_fraction * zt
        if nz.blob_fraction > 0:
            small = np.empty((max(2, h // 12), max(2, w // 12)), np.float32)
            cv2.randn(small, 0, 1)  # type: ignore[call-overload]
            field = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
            # a Gaussian field (std ~0.6 after interpolation) above the quantile of blob_fraction
            thr = 0.6 * _normal_quantile(1.0 - nz.blob_fraction)
            valid &= field < thr
        if nz.dropout_fraction > 0:
            u = np.empty((h, w), np.float32)
            cv2.randu(u, 0, 1)  # type: ignore[call-overload]
            valid &= u >= nz.dropout_fraction
        depth[~valid] = 0.0
        return image, depth


def _normal_quantile(p: float) -> float:
    """Standard normal quantile (Acklam's rational approximation is overkill here: bisection)."""
    lo, hi = -8.0, 8.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if 0.5 * (1.0 + math.erf(mid / math.sqrt(2.0))) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
