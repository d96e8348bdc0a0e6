"""Photo data sets on disk: a folder of data sets, each ``images/`` and its reference poses.

The layout the field's benchmarks share (COLMAP's, ETH3D's, the Image
Matching Challenge's)::

    ROOT/
      fountain-P11/
        images/            the photos
        sparse/0/          reference poses: a COLMAP model (text or binary),
                           or sparse/, or a Bundler .out beside images/
      kermit/
        images/
        bundle.out         (its list.txt beside it names the photos)

Every subfolder of ROOT holding ``images/`` is a data set, named by its
folder; its reference is optional (without one, a method's run registers
and places points but has no pose score). A data set is identified by its
content (:func:`dataset_digest`), never by where it lies.
"""

from __future__ import annotations

from pathlib import Path

from mpe3d.errors import MpeError

IMAGES = "images"


def photo_sets(root: str | Path) -> list[str]:
    """The data sets under ``root``: its subfolders holding ``images/``, by name."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise MpeError(f"photos.root: {root}: no such folder")
    return sorted(p.name for p in root.iterdir() if (p / IMAGES).is_dir())


def set_folder(root: str | Path | None, name: str) -> Path:
    """The folder of data set ``name`` under ``root``, checked."""
    if root is None:
        raise MpeError(f"photos.set={name}: a data set folder needs photos.root=DIR, the folder holding it",
                       key="photos.root")
    folder = Path(root).expanduser() / name
    if not (folder / IMAGES).is_dir():
        found = photo_sets(root)
        offered = f" (it has: {', '.join(found)})" if found else " (it has no subfolder holding images/)"
        raise MpeError(f"photos.set: {folder} holds no {IMAGES}/ folder{offered}", key="photos.set")
    return folder


def find_reference(folder: Path) -> Path | None:
    """The data set's reference poses (:func:`~.references.reference_in`), or None."""
    from mpe3d.harness.userdata.references import reference_in

    return reference_in(folder)


def dataset_digest(folder: Path) -> str:
    """What identifies a data set: its photos' bytes and its reference's (names
    relative to it), whatever the folder is called or wherever it lies."""
    import hashlib

    from mpe3d.harness.userdata.formats import content_digest

    reference = find_reference(folder)
    parts = [content_digest(folder / IMAGES)]
    if reference is not None:
        parts.append(content_digest(reference))
        listed = reference.parent / "list.txt"
        if reference.suffix == ".out" and listed.is_file():  # the names of a Bundler file's cameras
            parts.append(content_digest(listed))
    return "sha256:" + hashlib.sha256("\n".join(parts).encode()).hexdigest()
