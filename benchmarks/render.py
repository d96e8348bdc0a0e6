"""Rendering the colmap experiment's photos, against the first renderer, in one run.

    python benchmarks/render.py [--photos 25] [--size 400] [--shape chair]

One JSON line: seconds a photo of :func:`mpe3d.harness.scene.rendering.render`
and of the reference below (every ray cast, the texture's value noise as
whole-array NumPy, as the renderer was before issue 31), their ratio (target
>= 2), and whether the photos are the same bytes. The photos are every
(250 / photos)-th of the experiment's 250-camera spiral.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from mpe3d.harness.scene import rendering, shapes


def reference_noise(points: np.ndarray, seed: int) -> np.ndarray:
    """The value noise of ``photos``' module doc, array by array."""
    rng = np.random.default_rng(seed)
    perm, values = rng.permutation(256), rng.random(256)
    total, amplitude, norm = np.zeros(len(points)), 1.0, 0.0
    for i, frequency in enumerate(rendering.OCTAVES):
        p = points * frequency + 17.0 * i
        cell = np.floor(p).astype(np.int64)
        f = p - cell
        w = f * f * (3.0 - 2.0 * f)
        octave = np.zeros(len(points))
        for corner in np.ndindex(2, 2, 2):
            c = cell + corner
            h = perm[(perm[(perm[c[:, 0] & 255] + c[:, 1]) & 255] + c[:, 2]) & 255]
            octave += np.prod(np.where(corner, w, 1.0 - w), axis=1) * values[h]
        total += amplitude * octave
        norm += amplitude
        amplitude *= rendering.OCTAVE_GAIN
    return total / norm


def reference_render(mesh, cameras, seed: int = 0, supersample: int = 2) -> np.ndarray:
    """Every ray of every pixel cast, the albedo by :func:`reference_noise`."""
    H, W, s = cameras.height, cameras.width, supersample
    offsets = (np.arange(s) + 0.5) / s
    uu, vv = np.meshgrid((np.arange(W)[:, None] + offsets[None]).ravel(),
                         (np.arange(H)[:, None] + offsets[None]).ravel())
    rays_cam = np.stack([(uu - cameras.principal_point[0]) / cameras.focal,
                         (vv - cameras.principal_point[1]) / cameras.focal,
                         np.ones_like(uu)], axis=-1).reshape(-1, 3)
    rays_cam /= np.linalg.norm(rays_cam, axis=1, keepdims=True)
    out = np.empty((len(cameras), H, W), dtype=np.uint8)
    for k, (R, centre) in enumerate(zip(cameras.rotations, cameras.centres)):
        directions = rays_cam @ R
        tri, ray, where = mesh.ray.intersects_id(np.broadcast_to(centre, directions.shape),
                                                 directions, multiple_hits=False,
                                                 return_locations=True)
        shade = np.zeros(len(directions))
        albedo = np.clip(0.5 + 2.5 * (reference_noise(where, seed) - 0.5), 0.05, 1.0)
        shade[ray] = albedo * (rendering.AMBIENT + (1.0 - rendering.AMBIENT)
                               * np.abs(mesh.face_normals[tri] @ rendering.LIGHT))
        pixels = shade.reshape(H, s, W, s).mean(axis=(1, 3))
        out[k] = np.round(255.0 * np.clip(pixels, 0.0, 1.0)).astype(np.uint8)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=int, default=25)
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--shape", default="chair")
    args = parser.parse_args(argv)
    mesh = shapes.load_shape(args.shape)
    spiral = rendering.spiral_cameras(250, size=args.size)
    pick = np.linspace(0, 249, args.photos).round().astype(int)
    cameras = rendering.PhotoCameras(spiral.rotations[pick], spiral.translations[pick], spiral.focal,
                                  args.size, args.size)
    first = rendering.PhotoCameras(spiral.rotations[:1], spiral.translations[:1], spiral.focal,
                                args.size, args.size)
    rendering.render(mesh, first)  # the compiled noise loaded, the ray scene built: not timed
    seconds = {}
    for name, renderer in (("reference", reference_render), ("mpe3d", rendering.render)):
        start = time.perf_counter()
        images = renderer(mesh, cameras)
        seconds[name] = (time.perf_counter() - start) / args.photos
        seconds[name + "_images"] = images
    print(json.dumps({"benchmark": "render", "shape": args.shape, "photos": args.photos,
                      "size": args.size, "mpe3d_s_per_photo": round(seconds["mpe3d"], 4),
                      "reference_s_per_photo": round(seconds["reference"], 4),
                      "ratio": round(seconds["reference"] / seconds["mpe3d"], 2), "target_ratio": 2,
                      "same_bytes": bool(np.array_equal(seconds["mpe3d_images"],
                                                        seconds["reference_images"]))}))


if __name__ == "__main__":
    main()
