"""The pinhole camera model: intrinsics, extrinsics and every world ↔ camera ↔ pixel conversion.

Conventions (used everywhere in the studio):

* world frame: the scene's MuJoCo world frame, metres;
* camera frame: x right, y down, z forward (optical axis), metres — the OpenCV convention;
* pixel frame: u to the right, v down, origin at the top-left corner of the top-left pixel, so the
  centre of pixel (i, j) is (j + 0.5, i + 0.5).

MuJoCo cameras look along their local −z with y up; :func:`from_mujoco` converts. All functions take
arrays of points with the coordinate in the last axis and keep leading axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# MuJoCo camera axes (x right, y up, z backward) -> OpenCV camera axes (x right, y down, z forward).
_MJ_TO_CV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class CameraModel:
    """A calibrated pinhole camera.

    Attributes:
        width: image width in pixels.
        height: image height in pixels.
        K: (3, 3) intrinsic matrix in pixels.
        T_world_cam: (4, 4) pose of the camera in the world (maps camera-frame points to world).
    """

    width: int
    height: int
    K: np.ndarray
    T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.T_world_cam, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"CameraModel.K must be (3, 3), got {K.shape}")
        if T.shape != (4, 4):
            raise ValueError(f"CameraModel.T_world_cam must be (4, 4), got {T.shape}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"CameraModel size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_world_cam", T)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fovy(cls, fovy_deg: float, width: int, height: int, T_world_cam: np.ndarray) -> CameraModel:
        """A camera with square pixels and the principal point at the image centre (MuJoCo's model)."""
        f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2.0)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, K, T_world_cam)

    @classmethod
    def from_mujoco(cls, model, data, camera: str | int, width: int, height: int) -> CameraModel:
        """The exact camera model of a MuJoCo camera after ``mj_forward`` (fixed or moving)."""
        import mujoco

        cam_id = (
            camera
            if isinstance(camera, int)
            else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        )
        if cam_id < 0:
            raise KeyError(f"no camera named {camera!r} in the model")
        R_world_mjcam = data.cam_xmat[cam_id].reshape(3, 3)
        T = np.eye(4)
        T[:3, :3] = R_world_mjcam @ _MJ_TO_CV
        T[:3, 3] = data.cam_xpos[cam_id]
        return cls.from_fovy(float(model.cam_fovy[cam_id]), width, height, T)

    def resized(self, height: int, width: int) -> CameraModel:
        """The same camera with its image resampled to (height, width) (pixel-area scaling)."""
        S = np.diag([width / self.width, height / self.height, 1.0])
        return CameraModel(width, height, S @ self.K, self.T_world_cam)

    def with_pixel_affine(self, A: np.ndarray, height: int, width: int) -> CameraModel:
        """The virtual camera seeing the image warped by the pixel-space affine map ``A`` (3×3, last row 0 0 1).

        Any crop, translation, flip or resize of an image is such a map; projecting a world point with the
        returned camera lands exactly where the warped image shows it.
        """
        A = np.asarray(A, dtype=np.float64)
        if A.shape != (3, 3) or not np.allclose(A[2], [0.0, 0.0, 1.0]):
            raise ValueError(f"pixel affine map must be 3x3 with last row [0, 0, 1], got {A}")
        return CameraModel(width, height, A @ self.K, self.T_world_cam)

    # ------------------------------------------------------------------ frames
    @property
    def T_cam_world(self) -> np.ndarray:
        R = self.T_world_cam[:3, :3]
        t = self.T_world_cam[:3, 3]
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ t
        return T

    def world_to_cam(self, p_world: np.ndarray) -> np.ndarray:
        p = np.asarray(p_world, dtype=np.float64)
        T = self.T_cam_world
        return p @ T[:3, :3].T + T[:3, 3]

    def cam_to_world(self, p_cam: np.ndarray) -> np.ndarray:
        p = np.asarray(p_cam, dtype=np.float64)
        return p @ self.T_world_cam[:3, :3].T + self.T_world_cam[:3, 3]

    def cam_to_pixel(self, p_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame points to pixels (u, v). Points must be in front of the camera (z > 0)."""
        p = np.asarray(p_cam, dtype=np.float64)
        uvw = p @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]

    def pixel_to_cam(self, uv: np.ndarray, depth: np.ndarray | float) -> np.ndarray:
        """Back-project pixels at the given depth (camera z, metres) to camera-frame points."""
        uv = np.asarray(uv, dtype=np.float64)
        z = np.asarray(depth, dtype=np.float64)
        ones = np.ones((*uv.shape[:-1], 1))
        rays = np.concatenate([uv, ones], axis=-1) @ np.linalg.inv(self.K).T
        return rays * z[..., None] if z.ndim == uv.ndim - 1 else rays * z

    def world_to_pixel(self, p_world: np.ndarray) -> np.ndarray:
        return self.cam_to_pixel(self.world_to_cam(p_world))

    def pixel_to_world(self, uv: np.ndarray, depth: np.ndarray | float) -> np.ndarray:
        return self.cam_to_world(self.pixel_to_cam(uv, depth))

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "T_world_cam": self.T_world_cam.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> CameraModel:
        return cls(int(d["width"]), int(d["height"]), np.asarray(d["K"]), np.asarray(d["T_world_cam"]))
