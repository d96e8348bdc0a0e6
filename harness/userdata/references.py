"""Reference camera poses: what a reconstruction of photos is scored against.

A reference is a COLMAP model (a ``sparse/0`` or ``sparse`` folder, text or
binary, or the folder holding one) or a Bundler v0.3 ``.out`` file, its
cameras named by the ``list.txt`` beside it (the first word of each line,
any folder dropped), or else by the photos in name order. Its poses come
back in COLMAP's convention, ``x_cam = R x + t`` with the camera looking
down +z and y down: Bundler's cameras look down -z with y up, and
:mod:`.bundler`'s reader turns them (R' = F R, t' = F t, F = diag(1, -1, -1)).

:func:`poses_of` gives a reconstruction's poses in the same form; the score
itself is :func:`mpe3d.harness.scene.metrics.score_poses`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.harness.userdata import bundler

MODEL_FILES = ("cameras", "images")  # what a COLMAP model folder holds at least, .bin or .txt
LIST_FILE = "list.txt"  # Bundler's photo list, one photo per camera, in camera order


@dataclass(frozen=True)
class Reference:
    """Reference poses by photo name, ``(R, t)`` world -> camera (COLMAP's)."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]]  # the posed photos
    source: str  # the model folder or .out file read
    photos: int  # the photos the reference lists, posed or not
    unposed: tuple[str, ...] = ()  # listed but not posed (a Bundler camera of f = 0)
    notes: tuple[str, ...] = ()  # what a reader of the scores should know: its photos the folder lacks


def read_reference(path, photo_names=None) -> Reference:
    """The reference poses at ``path``: a COLMAP model folder (or a folder
    holding ``sparse/0`` or ``sparse``) or a Bundler ``.out`` file.

    ``photo_names`` names a Bundler file's cameras when no ``list.txt`` is
    beside it (sorted by name: camera k is the k-th). A COLMAP model lists
    its registered images only, so ``photos`` is their number. A Bundler
    camera with no point seen in it is counted as not posed, as Bundler's
    own unregistered cameras (all zeros) are.
    """
    path, photo_names = Path(path), None if photo_names is None else list(photo_names)
    if not path.exists():
        raise MpeError(f"{path}: no such file or folder (a reference: a COLMAP model folder or a Bundler .out)")
    found = path if path.is_file() else _model_folder(path)
    reference = _read_bundler(found, photo_names) if found.is_file() else _read_colmap(found)
    return reference if photo_names is None else _against_photos(reference, photo_names)


def _against_photos(reference: Reference, photo_names: list[str]) -> Reference:
    """The reference, refused when it names none of the photos (every pair
    would score 180 degrees, whatever the method), with a note when the
    photos lack some of its own (every method's AUC is then capped)."""
    if not photo_names:  # no photo to name: reading them says why, in a line of its own
        return reference
    here = {_base(n) for n in photo_names}
    listed = [*reference.poses, *reference.unposed]
    missing = [n for n in listed if _base(n) not in here]
    if len(missing) == len(listed):
        raise MpeError(f"{reference.source}: none of its {len(listed)} photos is among the {len(photo_names)} "
                       f"photos given (it names e.g. '{listed[0]}', the photos e.g. '{sorted(photo_names)[0]}'); "
                       "a reference names photos by their file names")
    posed = {_base(n) for n in reference.poses}
    unposed = [n for n in photo_names if _base(n) not in posed]
    notes = [f"{len(missing)} of the reference's {len(listed)} photos are not among the photos "
             f"({_some(missing)}): scored as unregistered by every method"] if missing else []
    if unposed:  # COLMAP's benchmark: a registered photo the reference does not pose is a registered outlier
        notes.append(f"{len(unposed)} of the {len(photo_names)} photos have no reference pose ({_some(unposed)}): "
                     "a method that registers one scores 180 degrees for each of its pairs")
    return replace(reference, notes=(*reference.notes, *notes))


def _some(names: list[str]) -> str:
    return ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")


def _base(name: str) -> str:
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def reference_in(folder: Path) -> Path | None:
    """A data set's reference beside its ``images/``: a COLMAP model in
    ``sparse/0`` or ``sparse``, or its one Bundler ``.out``; None when it has
    none. Two ``.out`` files are ambiguous: one line naming them."""
    for model in (folder / "sparse" / "0", folder / "sparse"):
        if _has_model(model):
            return model
    outs = sorted(folder.glob("*.out"))
    if len(outs) > 1:
        raise MpeError(f"{folder}: {len(outs)} Bundler files ({', '.join(p.name for p in outs)}); "
                       "keep the reference's alone beside images/")
    return outs[0] if outs else None


def _has_model(folder: Path) -> bool:
    return all(any((folder / f"{name}{ext}").is_file() for ext in (".bin", ".txt")) for name in MODEL_FILES)


def _model_folder(path: Path) -> Path:
    """``path`` itself, or its ``sparse/0`` or ``sparse``, whichever holds a
    model first; else the one ``.out`` file in it."""
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if _has_model(folder):
            return folder
    outs = sorted(path.glob("*.out"))
    if len(outs) == 1:
        return outs[0]
    raise MpeError(f"{path}: no COLMAP model in it or in sparse/0 or sparse (cameras and images, .bin or "
                   f".txt){'' if not outs else f', and {len(outs)} .out files, not one'}")


def _read_colmap(folder: Path) -> Reference:
    from mpe3d.solvers.sfm import colmap

    model = colmap.read_model(folder)
    poses = {name: (image.rotation, image.translation) for name, image in model.images.items()}
    if not poses:
        raise MpeError(f"{folder}: the COLMAP model poses no image")
    return Reference(poses, str(folder), len(poses))


def _read_bundler(path: Path, photo_names) -> Reference:
    if bundler.sniff(path) != "bundler":
        raise MpeError(f"{path}: not a Bundler .out file (first line '{bundler.BUNDLER_HEADER}')")
    cameras = _camera_count(path)
    names = _camera_names(path, cameras, photo_names)
    poses = {names[k]: pose for k, pose in enumerate(bundler.read_bundle_poses(path)) if pose is not None}
    if not poses:
        raise MpeError(f"{path}: the Bundler file poses no camera (every one unregistered)")
    return Reference(poses, str(path), cameras, tuple(n for n in names if n not in poses))


def _camera_count(path: Path) -> int:
    with open(path, encoding="utf-8", errors="replace") as handle:
        handle.readline()
        fields = handle.readline().split()
    if len(fields) != 2 or not all(f.isdigit() for f in fields):
        raise MpeError(f"{path}: line 2: expected '<cameras> <points>', got '{' '.join(fields)}'")
    return int(fields[0])


def _camera_names(path: Path, cameras: int, photo_names) -> list[str]:
    """Camera k's photo: line k of ``list.txt`` beside ``path``, else the k-th of ``photo_names`` by name."""
    listing = path.parent / LIST_FILE
    if listing.is_file():
        lines = listing.read_text(encoding="utf-8", errors="replace").splitlines()
        names = [_list_name(line) for line in lines if line.strip()]
        where = str(listing)
    elif photo_names is not None:
        names, where = sorted(photo_names), "the photos"
    else:
        raise MpeError(f"{path}: no {LIST_FILE} beside it to name its {cameras} cameras, and no photos given")
    if len(names) != cameras:
        raise MpeError(f"{where}: {len(names)} photo names for the {cameras} cameras of {path}")
    if len(set(names)) != len(names):
        raise MpeError(f"{where}: a photo named twice")
    return names


def _list_name(line: str) -> str:
    """A ``list.txt`` line's photo: its first word (Bundler writes the focal
    length after it), without any folder."""
    return _base(line.split()[0])


def unscored(result) -> str | None:
    """Why views the solve registered have no pose to score (an affine
    camera: no centre), or None when every registered view has one."""
    affine = [c.view for c in result.cameras if c.registered and c.rotation is not None and c.translation is None]
    if not affine:
        return None
    return (f"{len(affine)} registered views have an affine camera (the photos showed too little perspective for "
            "camera=auto to keep the pinhole): an affine camera has no centre, so they score as unregistered "
            "(ask the camera perspective or radial to score them)")


def poses_of(result) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{view name: (R, t)}`` of a :class:`~mpe3d.harness.userdata.results.Result`'s
    registered pinhole cameras. An affine camera (no translation along its
    axis, hence no centre), a given 3x4 matrix and a view the solve left out
    are absent: a pose without a centre cannot be scored, so they count as
    not registered."""
    return {c.view: (c.rotation, c.translation) for c in result.cameras
            if c.registered and c.rotation is not None and c.translation is not None}
