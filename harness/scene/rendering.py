"""Photos of a mesh: textured, shaded pinhole renderings from known cameras.

The paper's COLMAP experiment (Section "Exploratory Integration with COLMAP")
rendered a ShapeNet chair with Blender, its materials changed "to provide
sufficient texture variation for feature matching"; it gives no image size,
camera path or texture. Ours, chosen so that SIFT finds features that repeat
from view to view, and documented here because the paper does not say:

* **Cameras**: pinholes in COLMAP's convention (x_cam = R x + t, +z forward,
  image y down, pixel centres at half-integers), with an optional lens: radial
  distortion k1, k2 of the normalised image point as COLMAP's RADIAL camera
  applies it (x_d = x (1 + k1 r^2 + k2 r^4)), on a closed spiral round the
  object (centred, unit bounding-box diagonal, y up): ``turns`` turns of
  azimuth while the elevation swings from ``elevation[0]`` to ``elevation[1]``
  and back, at ``distance`` from the centre, each looking at the centre. The
  focal length makes the bounding sphere fill ``fill`` of the image's width.
  Consecutive photos are neighbours on the path (sequential matching).
* **Texture**: the albedo is fractal value noise of the 3D surface position
  (five octaves, 4 to 64 cycles per unit), so a surface patch looks the same
  from every camera; it is fixed by ``seed``.
* **Shading**: Lambertian under one light fixed in the world plus ambient,
  two-sided (the meshes' face orientations are not all consistent), on a
  black background. ``supersample`` x ``supersample`` rays per pixel are
  averaged, which smooths the silhouettes and facet edges SIFT would
  otherwise fire on.

Rays are cast with embree through trimesh (``mesh.ray``); no OpenGL.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from numba import njit

LIGHT = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])  # world frame, from above
AMBIENT = 0.3
OCTAVES = (4.0, 8.0, 16.0, 32.0, 64.0)  # texture frequencies, cycles per unit length
OCTAVE_GAIN = 0.7  # each finer octave's amplitude, relative to the one before


@dataclass(frozen=True)
class PhotoCameras:
    """K pinhole cameras sharing one intrinsic matrix (COLMAP's PINHOLE model)."""

    rotations: np.ndarray  # (K, 3, 3) world -> camera
    translations: np.ndarray  # (K, 3)
    focal: float  # pixels, fx = fy
    width: int
    height: int
    distortion: tuple[float, float] = (0.0, 0.0)  # k1, k2 (COLMAP's RADIAL camera)

    @property
    def principal_point(self) -> np.ndarray:
        return np.array([self.width / 2.0, self.height / 2.0])

    @property
    def centres(self) -> np.ndarray:
        """(K, 3) camera centres in the world: -R^T t."""
        return -np.einsum("kji,kj->ki", self.rotations, self.translations)

    @property
    def intrinsics(self) -> np.ndarray:
        cx, cy = self.principal_point
        return np.array([[self.focal, 0.0, cx], [0.0, self.focal, cy], [0.0, 0.0, 1.0]])

    def matrices(self) -> np.ndarray:
        """(K, 3, 4) camera matrices K [R | t]."""
        Rt = np.concatenate([self.rotations, self.translations[:, :, None]], axis=2)
        return self.intrinsics @ Rt

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (K, N, 2) of ``points`` in every view, and their depths (K, N)."""
        cam = np.einsum("kij,nj->kni", self.rotations, points) + self.translations[:, None]
        depth = cam[..., 2]
        return self.focal * self.distorted(cam[..., :2] / depth[..., None]) + self.principal_point, depth

    def distorted(self, n: np.ndarray) -> np.ndarray:
        """Normalised image points (..., 2) through the lens."""
        k1, k2 = self.distortion
        if k1 == 0.0 and k2 == 0.0:
            return n
        r2 = np.sum(n ** 2, axis=-1, keepdims=True)
        return n * (1.0 + k1 * r2 + k2 * r2 ** 2)

    def undistorted(self, d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """The normalised points whose :meth:`distorted` images are ``d`` (..., 2):
        fixed-point iterations, which converge for the mild lenses photos have."""
        k1, k2 = self.distortion
        if k1 == 0.0 and k2 == 0.0:
            return d
        n = d.copy()
        for _ in range(iterations):
            r2 = np.sum(n ** 2, axis=-1, keepdims=True)
            n = d / (1.0 + k1 * r2 + k2 * r2 ** 2)
        return n

    def __len__(self) -> int:
        return len(self.rotations)


def look_at(centres: np.ndarray, target=np.zeros(3), up=np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """(K, 3, 3) world->camera rotations of cameras at ``centres`` looking at ``target``,
    image y pointing down along the world's ``-up``."""
    forward = target - centres
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, up)  # image x
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=1)


def spiral_cameras(count: int, *, size: int = 400, distance: float = 1.5,
                   elevation=(10.0, 50.0), turns: float = 2.0, fill: float = 0.85) -> PhotoCameras:
    """``count`` cameras on the closed spiral of the module doc, ``size`` x ``size`` pixels."""
    s = np.arange(count) / count
    azimuth = 2.0 * np.pi * turns * s
    lo, hi = np.radians(elevation)
    elev = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2.0 * np.pi * s))
    centres = distance * np.column_stack([np.cos(elev) * np.sin(azimuth), np.sin(elev),
                                          np.cos(elev) * np.cos(azimuth)])
    R = look_at(centres)
    t = -np.einsum("kij,kj->ki", R, centres)
    radius = 0.5  # of the bounding sphere of a unit-diagonal mesh
    focal = fill * (size / 2.0) * np.sqrt(distance ** 2 - radius ** 2) / radius
    return PhotoCameras(R, t, float(focal), size, size)


def photo_spiral(count: int, size: int, seed: int, fill: float = 0.85) -> PhotoCameras:
    """The photo set of a rendered structure-from-motion data set: the spiral of
    :func:`spiral_cameras` with photos about 15-18 degrees apart (the spacing
    photogrammetry guides ask for: half a turn for 10 photos, one for 25, two
    for 100 and more), turned about the vertical by an angle drawn from ``seed``."""
    cams = spiral_cameras(count, size=size, turns=min(2.0, max(0.5, count / 25)), fill=fill)
    a = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return PhotoCameras(cams.rotations @ turn.T, cams.translations, cams.focal, cams.width, cams.height)


def _lattice(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.permutation(256), rng.random(256)


def value_noise(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Fractal value noise in [0, 1] at 3D ``points`` (N, 3): smooth, view-independent."""
    perm, values = _lattice(seed)
    return _value_noise(np.ascontiguousarray(points, dtype=np.float64), perm.astype(np.int64),
                        values, np.array(OCTAVES), OCTAVE_GAIN)


@njit(cache=True, nogil=True)
def _value_noise(points, perm, values, octaves, gain):
    """Each octave: the lattice values at the 8 corners of the point's cell
    (hashed through ``perm``), blended by smoothstep weights; octaves summed
    with ``gain``'s decaying amplitudes and normalised. One pass a point (the
    array version made 40 temporaries of N), with the same operations in the
    same order, so the same bits."""
    out = np.empty(points.shape[0])
    for t in range(points.shape[0]):
        total, amplitude, norm = 0.0, 1.0, 0.0
        for i in range(octaves.shape[0]):
            shift = 17.0 * i  # each octave its own patch of the lattice
            p0 = points[t, 0] * octaves[i] + shift
            p1 = points[t, 1] * octaves[i] + shift
            p2 = points[t, 2] * octaves[i] + shift
            c0, c1, c2 = np.int64(np.floor(p0)), np.int64(np.floor(p1)), np.int64(np.floor(p2))
            f0, f1, f2 = p0 - c0, p1 - c1, p2 - c2
            # smoothstep: no creases at the lattice planes
            w0, w1, w2 = f0 * f0 * (3.0 - 2.0 * f0), f1 * f1 * (3.0 - 2.0 * f1), f2 * f2 * (3.0 - 2.0 * f2)
            octave = 0.0
            for a in range(2):
                for b in range(2):
                    for c in range(2):
                        h = perm[(perm[(perm[(c0 + a) & 255] + c1 + b) & 255] + c2 + c) & 255]
                        weight = ((w0 if a else 1.0 - w0) * (w1 if b else 1.0 - w1)) \
                            * (w2 if c else 1.0 - w2)
                        octave += weight * values[h]
            total += amplitude * octave
            norm += amplitude
            amplitude *= gain
        out[t] = total / norm
    return out


def _albedo(points: np.ndarray, seed: int) -> np.ndarray:
    """High-contrast albedo: the noise stretched round its mean (fractal sums bunch up)."""
    n = value_noise(points, seed)
    return np.clip(0.5 + 2.5 * (n - 0.5), 0.05, 1.0)


def render(mesh: trimesh.Trimesh, cameras: PhotoCameras, *, seed: int = 0,
           supersample: int = 2) -> np.ndarray:
    """(K, height, width) uint8 grey images of ``mesh`` from ``cameras``."""
    H, W, s = cameras.height, cameras.width, supersample
    offsets = (np.arange(s) + 0.5) / s
    u = (np.arange(W)[:, None] + offsets[None]).ravel()
    v = (np.arange(H)[:, None] + offsets[None]).ravel()
    uu, vv = np.meshgrid(u, v)  # (H s, W s)
    seen = cameras.undistorted(np.stack([(uu - cameras.principal_point[0]) / cameras.focal,
                                         (vv - cameras.principal_point[1]) / cameras.focal], axis=-1))
    rays_cam = np.concatenate([seen, np.ones_like(uu)[..., None]], axis=-1).reshape(-1, 3)
    rays_cam /= np.linalg.norm(rays_cam, axis=1, keepdims=True)
    normals = mesh.face_normals
    out = np.empty((len(cameras), H, W), dtype=np.uint8)
    for k, (R, centre) in enumerate(zip(cameras.rotations, cameras.centres)):
        directions = rays_cam @ R  # camera -> world: R^T d, as row vectors
        # only the rays inside the box round the projected vertices can hit: the
        # rest (half the photo) are not cast. Each ray's hit is its own, so the
        # pixels are the same bits as casting them all.
        cast = np.flatnonzero(_inside_projection(mesh.vertices, R, centre, cameras, uu, vv))
        origins = np.broadcast_to(centre, (len(cast), 3))
        tri, ray, where = mesh.ray.intersects_id(origins, directions[cast], multiple_hits=False,
                                                 return_locations=True)
        ray = cast[ray]
        shade = np.zeros(len(directions))
        lambert = np.abs(normals[tri] @ LIGHT)
        shade[ray] = _albedo(where, seed) * (AMBIENT + (1.0 - AMBIENT) * lambert)
        pixels = shade.reshape(H, s, W, s).mean(axis=(1, 3))
        out[k] = np.round(255.0 * np.clip(pixels, 0.0, 1.0)).astype(np.uint8)
    return out


def _inside_projection(vertices, R, centre, cameras: PhotoCameras, uu, vv) -> np.ndarray:
    """Which sample positions (uu, vv) lie within a pixel of the box round the
    mesh's projected vertices: a triangle in front of the camera projects
    inside their convex hull. All rays when a vertex is not in front."""
    x_cam = (vertices - centre) @ R.T
    if np.any(x_cam[:, 2] <= 0):
        return np.ones(uu.size, dtype=bool)
    u, v = (cameras.focal * cameras.distorted(x_cam[:, :2] / x_cam[:, 2:]) + cameras.principal_point).T
    return ((uu >= u.min() - 1) & (uu <= u.max() + 1) & (vv >= v.min() - 1)
            & (vv <= v.max() + 1)).ravel()


def save_images(images: np.ndarray, folder: Path, stem: str = "image") -> list[str]:
    """Write each image as ``folder/stem_0000.png``; returns the file names in order."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{stem}_{k:04d}.png" for k in range(len(images))]
    for name, image in zip(names, images):
        Image.fromarray(image).save(folder / name)
    return names
