"""Camera models for keypoints: how a 3D point x lands on a view's image, in pixels.

Three models, from the paper's to a real camera's:

* ``orthographic`` (the paper's): u = R[:2] x + t, a rotation and a 2D
  translation per view, image units shared by all views;
* ``scaled`` (weak perspective): u = s R[:2] x + t, plus a scale per view,
  since real views differ in zoom and distance;
* ``perspective`` (pinhole): u = f (R x + T)[:2] / (R x + T)[2] + c, with a
  3D translation per view, the focal length f per view or shared, and the
  principal point c fixed (given, or the centre of the keypoints);
* ``radial`` (the Bundler/BAL camera): the pinhole with radial distortion,
  u = f d(n) n + c with n = (R x + T)[:2] / (R x + T)[2] and
  d(n) = 1 + k1 |n|^2 + k2 |n|^4; f, k1 and k2 per view (as Bundler and BAL
  files carry them) or shared by all views (one lens).

Rotations are R = R0 Exp([w]), with w the parameter and R0 the last
anchor, so that no parametrisation singularity is ever near: the Jacobian
d(R v)/dw = -R [v]x J_r(w) uses SO(3)'s right Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpe3d.options import CAMERA_MODELS
from mpe3d.solvers.linalg import matvec_by_group
from mpe3d.solvers.sfm.kernels import grouped_matvecs, pose_jacobians

CAMERAS = tuple(CAMERA_MODELS)  # the models a camera array can hold
PINHOLES = ("perspective", "radial")  # 3D translation, depth, a focal length
# The affine camera u = A x + t (A any 2x3) is no camera model a user picks: it is
# the start, and the floor that no metric model's error can go below.
AFFINE = "affine"
# Known 3x4 camera matrices, u = (P [x; 1])[:2] / (P [x; 1])[2]: nothing to fit.
MATRIX = "matrix"


def hat(v: np.ndarray) -> np.ndarray:
    """[v]x for each row of ``v`` (..., 3) -> (..., 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _series(theta: np.ndarray):
    """(sin t)/t, (1 - cos t)/t^2 and (t - sin t)/t^3, stable near t = 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    t2 = theta ** 2
    a = np.where(small, 1 - t2 / 6, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24, (1 - np.cos(t)) / t ** 2)
    c = np.where(small, 1 / 6 - t2 / 120, (t - np.sin(t)) / t ** 3)
    return a, b, c


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (K, 3) -> rotations (K, 3, 3)."""
    a, b, _ = _series(np.linalg.norm(w, axis=-1))
    W = hat(w)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * W @ W


def right_jacobian(w: np.ndarray) -> np.ndarray:
    """J_r(w) of SO(3), (K, 3) -> (K, 3, 3)."""
    _, b, c = _series(np.linalg.norm(w, axis=-1))
    W = hat(w)
    return np.eye(3) - b[:, None, None] * W + c[:, None, None] * W @ W


def complete_rotation(P: np.ndarray) -> np.ndarray:
    """(K, 2, 3) orthonormal rows -> (K, 3, 3) rotations with those first rows."""
    return np.concatenate([P, np.cross(P[:, 0], P[:, 1])[:, None]], axis=1)


@dataclass
class Cameras:
    """K cameras of one model, as their anchor rotations and their parameters.

    ``params`` per view: ``w`` (3) then ``t`` (2; 3 for the pinholes), then
    ``log s`` for scaled, ``log f`` for perspective with per-view focal
    lengths and ``log f, k1, k2`` for radial with per-view intrinsics. Shared
    intrinsics are the global parameters: ``[log f]`` or ``[log f, k1, k2]``.
    """

    model: str
    rotations: np.ndarray  # (K, 3, 3) anchors R0; (K, 3, 4) camera matrices for MATRIX
    params: np.ndarray  # (K, per_view)
    shared: np.ndarray  # (0,), (1,) = [log f] or (3,) = [log f, k1, k2]
    principal_point: np.ndarray  # (2,), pinholes only

    @property
    def per_view(self) -> int:
        return self.params.shape[1]

    def vector(self) -> np.ndarray:
        return np.concatenate([self.params.ravel(), self.shared])

    def with_vector(self, v: np.ndarray) -> "Cameras":
        K = len(self.rotations)
        return Cameras(self.model, self.rotations, v[:K * self.per_view].reshape(K, -1),
                       v[K * self.per_view:], self.principal_point)

    def take(self, views: np.ndarray) -> "Cameras":
        """The cameras of ``views`` alone (the shared intrinsics with them)."""
        return Cameras(self.model, self.rotations[views], self.params[views], self.shared.copy(),
                       self.principal_point)

    def put(self, views: np.ndarray, part: "Cameras") -> "Cameras":
        """These cameras with those of ``views`` (and the shared intrinsics) from ``part``."""
        mine = self.reanchored()
        part = part.reanchored()
        rotations, params = mine.rotations.copy(), mine.params.copy()
        rotations[views], params[views] = part.rotations, part.params
        return Cameras(self.model, rotations, params, part.shared.copy(), self.principal_point)

    def reanchored(self) -> "Cameras":
        """The same cameras with w folded into R0 (w = 0 again)."""
        if self.model in (AFFINE, MATRIX):
            return self
        params = self.params.copy()
        params[:, :3] = 0.0
        return Cameras(self.model, self.current_rotations(), params, self.shared.copy(),
                       self.principal_point)

    def current_rotations(self) -> np.ndarray:
        return self.rotations @ exp_so3(self.params[:, :3])

    def focal(self) -> np.ndarray:
        """f per view (pinholes)."""
        K = len(self.rotations)
        if self.shared.size:
            return np.full(K, np.exp(self.shared[0]))
        return np.exp(self.params[:, 6])

    def distortion(self) -> np.ndarray:
        """(K, 2): k1, k2 per view (radial; zero for the other models)."""
        K = len(self.rotations)
        if self.model != "radial":
            return np.zeros((K, 2))
        if self.shared.size:
            return np.broadcast_to(self.shared[1:3], (K, 2)).copy()
        return self.params[:, 7:9].copy()

    def scale(self) -> np.ndarray:
        """The image scale per view: s (scaled), 1 (orthographic), f / depth of
        the origin (perspective)."""
        if self.model == "scaled":
            return np.exp(self.params[:, 5])
        if self.model == "orthographic":
            return np.ones(len(self.rotations))
        return self.focal() / self.params[:, 5]

    def project(self, X: np.ndarray, view: np.ndarray, point: np.ndarray) -> np.ndarray:
        """u_t for the observations (view[t], point[t]) of the points X, (T, 2)."""
        if self.model == AFFINE:
            A = self.params[:, :6].reshape(-1, 2, 3)
            return _matvecs(A, view, X, point) + self.params[view, 6:8]
        if self.model == MATRIX:
            p = _matvecs(self.rotations[:, :, :3], view, X, point) + self.rotations[view, :, 3]
            return p[:, :2] / p[:, 2:3]  # a matrix's overall sign is the user's: no cheirality
        R = self.current_rotations()
        q = _matvecs(R, view, X, point)
        if self.model not in PINHOLES:
            s = self.scale()[view, None]
            return s * q[:, :2] + self.params[view, 3:5]
        p = q + self.params[view, 3:6]
        depth = np.where(p[:, 2:3] > 0, p[:, 2:3], np.nan)  # behind the camera: no image
        n = p[:, :2] / depth
        if self.model == "radial":
            k = self.distortion()[view]
            r2 = np.sum(n ** 2, axis=1, keepdims=True)
            n = n * (1 + k[:, :1] * r2 + k[:, 1:] * r2 ** 2)
        return self.focal()[view, None] * n + self.principal_point

    def jacobian_blocks(self, X, view, point):
        """du_t/dx_i (T, 2, 3) and du_t/d(view parameters) (T, 2, per_view),
        plus du_t/d(shared) (T, 2, n_shared)."""
        if self.model not in (AFFINE, MATRIX, "radial"):
            return self._pose_blocks(X, view, point)
        T = len(view)
        x = X[point]
        if self.model == AFFINE:
            d_view = np.zeros((T, 2, 8))
            d_view[:, 0, 0:3], d_view[:, 1, 3:6] = x, x
            d_view[:, 0, 6] = d_view[:, 1, 7] = 1.0
            return self.params[view, :6].reshape(T, 2, 3), d_view, np.zeros((T, 2, 0))
        if self.model == MATRIX:
            P = self.rotations[view]
            p = np.einsum("tij,tj->ti", P[:, :, :3], x) + P[:, :, 3]
            u = p[:, :2] / p[:, 2:3]
            d_x = (P[:, :2, :3] - u[:, :, None] * P[:, 2:3, :3]) / p[:, 2:3, None]
            return d_x, np.zeros((T, 2, 0)), np.zeros((T, 2, 0))
        R = self.current_rotations()[view]
        q = np.einsum("tij,tj->ti", R, x)
        dq_dw = -R @ hat(x) @ right_jacobian(self.params[:, :3])[view]
        p = q + self.params[view, 3:6]
        n = p[:, :2] / p[:, 2:3]
        dn_dp = np.zeros((T, 2, 3))
        dn_dp[:, 0, 0] = dn_dp[:, 1, 1] = 1 / p[:, 2]
        dn_dp[:, :, 2] = -n / p[:, 2:3]
        du_dn, d_intrinsic = self._intrinsic_blocks(n, self.focal()[view], view)
        du_dp = du_dn @ dn_dp
        d_view = np.zeros((T, 2, self.per_view))
        d_view[:, :, :3] = du_dp @ dq_dw
        d_view[:, :, 3:6] = du_dp
        d_shared = np.zeros((T, 2, self.shared.size))
        if self.shared.size:
            d_shared[:] = d_intrinsic
        else:
            d_view[:, :, 6:] = d_intrinsic
        return du_dp @ R, d_view, d_shared

    def _pose_blocks(self, X, view, point):
        """:meth:`jacobian_blocks` of the orthographic, scaled and perspective
        cameras, by the compiled :func:`~mpe3d.solvers.kernels.pose_jacobians`
        (250 views x 3,000 points: 25 ms, against numpy's 120 ms with its
        (T, 3, 3) temporaries; the same bits)."""
        T, pinhole = len(view), self.model in PINHOLES
        d_x, d_view = np.empty((T, 2, 3)), np.zeros((T, 2, self.per_view))
        d_focal = np.empty((T, 2) if pinhole else (0, 2))
        factor = self.focal() if pinhole else self.scale()
        pose_jacobians(np.ascontiguousarray(X, dtype=float), np.asarray(view, dtype=np.int64),
                       np.asarray(point, dtype=np.int64), np.ascontiguousarray(self.current_rotations()),
                       np.ascontiguousarray(right_jacobian(self.params[:, :3])),
                       np.ascontiguousarray(self.params[:, 3:6] if pinhole else np.zeros((len(factor), 3))),
                       np.ascontiguousarray(factor, dtype=float), pinhole, d_x, d_view, d_focal)
        d_shared = np.zeros((T, 2, self.shared.size))
        if pinhole and self.shared.size:
            d_shared[:, :, 0] = d_focal
        elif pinhole:
            d_view[:, :, 6] = d_focal
        return d_x, d_view, d_shared

    def _intrinsic_blocks(self, n, f, view):
        """The radial camera's du/dn (T, 2, 2) and du/d(log f, k1, k2) (T, 2, 3)
        at the normalised image points n."""
        T = len(n)
        k = self.distortion()[view]
        r2 = np.sum(n ** 2, axis=1)
        d = 1 + k[:, 0] * r2 + k[:, 1] * r2 ** 2
        dd_dn = ((2 * k[:, 0] + 4 * k[:, 1] * r2)[:, None] * n)  # (T, 2)
        du_dn = f[:, None, None] * (d[:, None, None] * np.eye(2) + n[:, :, None] * dd_dn[:, None, :])
        fn = f[:, None] * n
        d_intrinsic = np.empty((T, 2, 3))
        d_intrinsic[:, :, 0] = d[:, None] * fn
        d_intrinsic[:, :, 1] = r2[:, None] * fn
        d_intrinsic[:, :, 2] = (r2 ** 2)[:, None] * fn
        return du_dn, d_intrinsic

    def projection_matrices(self) -> np.ndarray:
        """(K, 3, 4): u ~ P [x; 1], with last row (0, 0, 0, 1) for the affine models."""
        K = len(self.rotations)
        if self.model == MATRIX:
            return self.rotations
        P = np.zeros((K, 3, 4))
        P[:, 2, 3] = 1.0
        if self.model == AFFINE:
            P[:, :2, :3] = self.params[:, :6].reshape(K, 2, 3)
            P[:, :2, 3] = self.params[:, 6:8]
            return P
        R = self.current_rotations()
        if self.model in PINHOLES:  # radial: the pinhole without its distortion
            intrinsics = np.zeros((K, 3, 3))
            intrinsics[:, 0, 0] = intrinsics[:, 1, 1] = self.focal()
            intrinsics[:, :2, 2], intrinsics[:, 2, 2] = self.principal_point, 1.0
            return intrinsics @ np.concatenate([R, self.params[:, 3:6, None]], axis=2)
        P[:, :2, :3] = self.scale()[:, None, None] * R[:, :2]
        P[:, :2, 3] = self.params[:, 3:5]
        return P

    def matrices(self) -> list[dict]:
        """Each view's camera as plain numbers, for the report."""
        if self.model == MATRIX:
            return [{"P": P.tolist()} for P in self.rotations]
        R, P = self.current_rotations(), self.projection_matrices()
        out = []
        for k in range(len(R)):
            if self.model in PINHOLES:
                out.append({"focal_px": float(self.focal()[k]), "rotation": R[k].tolist(),
                            "translation": self.params[k, 3:6].tolist(), "P": P[k].tolist()})
                if self.model == "radial":
                    out[-1]["k1"], out[-1]["k2"] = (float(v) for v in self.distortion()[k])
            else:
                out.append({"scale": float(self.scale()[k]), "rotation": R[k].tolist(),
                            "translation_px": self.params[k, 3:5].tolist(),
                            "P": (self.scale()[k] * R[k, :2]).tolist()})
        return out


def known_matrices(P: np.ndarray) -> Cameras:
    """Cameras fixed to the 3x4 matrices P (K, 3, 4)."""
    P = np.asarray(P, dtype=float)
    return Cameras(MATRIX, P, np.zeros((len(P), 0)), np.zeros(0), np.zeros(2))


def affine_cameras(model: str, P: np.ndarray, scale: np.ndarray, t: np.ndarray,
                   focal: float | None = None, principal_point=None,
                   shared_focal: bool = True) -> Cameras:
    """Cameras of ``model`` from orthonormal rows P (K, 2, 3), per-view scales
    and 2D translations: exact for orthographic and scaled; for perspective,
    the pinhole camera at depth f / s that matches them at the origin."""
    K = len(P)
    R0 = complete_rotation(P)
    if model == "orthographic":
        params = np.concatenate([np.zeros((K, 3)), t], axis=1)
        return Cameras(model, R0, params, np.zeros(0), np.zeros(2))
    if model == "scaled":
        params = np.concatenate([np.zeros((K, 3)), t, np.log(scale)[:, None]], axis=1)
        return Cameras(model, R0, params, np.zeros(0), np.zeros(2))
    c = np.asarray(principal_point, dtype=float)
    depth = focal / scale
    T = np.concatenate([(t - c) / scale[:, None], depth[:, None]], axis=1)
    if shared_focal:
        params = np.concatenate([np.zeros((K, 3)), T], axis=1)
        return Cameras(model, R0, params, np.array([np.log(focal)]), c)
    params = np.concatenate([np.zeros((K, 3)), T, np.full((K, 1), np.log(focal))], axis=1)
    return Cameras(model, R0, params, np.zeros(0), c)


def radial_cameras(rotations: np.ndarray, translations: np.ndarray, focal: np.ndarray,
                   distortion: np.ndarray, principal_point=(0.0, 0.0),
                   shared: bool = False) -> Cameras:
    """Radial (Bundler/BAL) cameras from rotations (K, 3, 3), translations
    (K, 3), focal lengths (K,) and k1, k2 (K, 2); ``shared`` keeps one focal
    length and one k1, k2 (view 0's) for all views."""
    K = len(rotations)
    focal = np.broadcast_to(np.asarray(focal, dtype=float), (K,))
    distortion = np.broadcast_to(np.asarray(distortion, dtype=float), (K, 2))
    pose = np.concatenate([np.zeros((K, 3)), np.asarray(translations, dtype=float)], axis=1)
    c = np.asarray(principal_point, dtype=float)
    if shared:
        return Cameras("radial", np.asarray(rotations, dtype=float), pose,
                       np.array([np.log(focal[0]), *distortion[0]]), c)
    params = np.concatenate([pose, np.log(focal)[:, None], distortion], axis=1)
    return Cameras("radial", np.asarray(rotations, dtype=float), params, np.zeros(0), c)


def with_distortion(cameras: Cameras) -> Cameras:
    """Perspective cameras as radial ones with k1 = k2 = 0 (the start of a
    distortion fit); intrinsics stay shared when the focal length is."""
    if cameras.model != "perspective":
        raise ValueError(f"expected perspective cameras, got {cameras.model}")
    cam = cameras.reanchored()
    return radial_cameras(cam.rotations, cam.params[:, 3:6], cam.focal(),
                          np.zeros(2), cam.principal_point, shared=bool(cam.shared.size))


def _matvecs(M, view, X, point):
    """(T, a): M[view[t]] @ X[point[t]], compiled (:func:`~mpe3d.solvers.kernels.grouped_matvecs`):
    the bits of :func:`~mpe3d.solvers.linalg.matvec_by_group`'s per-view products.
    A view with one observation is left to that function: numpy's BLAS forms
    a one-row product by another kernel (gemv), which rounds otherwise."""
    view, point = np.asarray(view, dtype=np.int64), np.asarray(point, dtype=np.int64)
    out = grouped_matvecs(np.ascontiguousarray(M, dtype=float), view, np.ascontiguousarray(X, dtype=float),
                          point)
    single = np.bincount(view, minlength=len(M))[view] == 1
    if single.any():
        out[single] = matvec_by_group(M, view[single], X[point[single]])
    return out
