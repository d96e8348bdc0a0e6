"""What data a run reads, named as MLflow names a run's data set (a dataset
input: name, digest, source), so that the UI's Datasets column says it and
runs on the same data group together.

* ``pipeline=points``: the shape's mesh (a bundled asset, a user's file, a
  procedural solid or a plug-in's data set) and its sampling (``points``
  area-uniform samples);
* ``pipeline=colmap``: the photos rendered of that mesh (``images.count`` of
  ``images.size`` pixels);
* ``pipeline=tracks``: the keypoint data set ``tracks.path``, by its content.

The digest names the data, not where it lies: a mesh's or a data set's bytes
(:func:`~mpe3d.harness.userdata.formats.content_digest`) and the sampling.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

from mpe3d.harness.experiment.config import RENDERED, RunConfig, photo_set_folder, track_file

DIGEST_CHARS = 16  # MLflow keeps a data set's digest in at most 36 characters
NAME_CHARS = 500  # and its name in at most this many
_LOG = logging.getLogger(__name__)


def dataset_of(config: RunConfig) -> dict[str, str]:
    """The fields of ``config``'s MLflow dataset (``name``, ``digest``,
    ``source_type``, ``source``, ``profile``), or ``{}`` when its data cannot
    be read (the run itself then fails and says why): a name for the UI
    never costs a run its record."""
    try:
        if config["pipeline"] == "tracks":
            return _tracks(config)
        if config["pipeline"] == "photos" and config["photos.set"] != RENDERED:
            return _photo_folder(config)
        return _shape(config)
    except Exception:  # noqa: BLE001  (a plug-in's data set may raise anything)
        _LOG.warning("no MLflow data set for the run of %s", config["shape"], exc_info=True)
        return {}


def _tracks(config: RunConfig) -> dict[str, str]:
    from mpe3d.harness.userdata.formats import content_digest

    path = track_file(config.values, "tracks.path")
    # named as the sweep names it (realdata's house and dino are both keypoints.csv)
    return {"name": str(config["tracks.path"])[-NAME_CHARS:], "digest": _short(content_digest(path)),
            "source_type": "local", "source": _uri(path), "profile": json.dumps({"kind": "keypoint tracks"})}


def _photo_folder(config: RunConfig) -> dict[str, str]:
    from mpe3d.harness.userdata.photo_sets import IMAGES, dataset_digest

    folder = photo_set_folder(config.values)
    photos = sum(1 for p in (folder / IMAGES).iterdir() if p.is_file())
    return {"name": str(config["photos.set"])[-NAME_CHARS:], "digest": _short(dataset_digest(folder)),
            "source_type": "local", "source": _uri(folder), "profile": json.dumps({"files": photos})}


def shape_data(spec: str) -> str:
    """What a shape's data is: its mesh file's bytes, or a procedural or plug-in name."""
    from mpe3d.harness.scene import shapes
    from mpe3d.harness.userdata.formats import content_digest

    mesh = shapes.mesh_file(spec)
    return f"shape:{spec}" if mesh is None else content_digest(mesh)


def _shape(config: RunConfig) -> dict[str, str]:
    # here, not at the top: the parent process, which imports this module to
    # record a run whose worker died, need not load trimesh (0.5 s) for it
    from mpe3d.harness.scene import shapes

    spec = config["shape"]
    mesh = shapes.mesh_file(spec)
    # MLflow's own source formats (its CodeDatasetSource's, LocalArtifactDatasetSource's JSON)
    source_type, source = ("code", json.dumps({"tags": {"mpe3d.shape": spec}})) if mesh is None \
        else ("local", _uri(mesh))
    data = shape_data(spec)
    shown = spec if mesh is None or ":" in spec or spec in shapes.shape_names() else Path(spec).name  # a file: its name
    if config["pipeline"] in ("colmap", "photos"):
        sampling = {"photos": config["images.count"], "size_px": config["images.size"]}
        name = f"{shown} photos"
    else:
        sampling = {"points": config["points"], "sampling": "area-uniform"}
        name = shown
    digest = _short(json.dumps({"data": data, **sampling}, sort_keys=True))
    return {"name": name[-NAME_CHARS:], "digest": digest, "source_type": source_type, "source": source,
            "profile": json.dumps(sampling, sort_keys=True)}


def _uri(path: Path) -> str:
    return json.dumps({"uri": str(path.resolve())})


def _short(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:DIGEST_CHARS]

