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

from mpe3d.harness.experiment.config import RunConfig, track_file

DIGEST_CHARS = 16  # MLflow keeps a data set's digest in at most 36 characters


def dataset_of(config: RunConfig) -> dict[str, str]:
    """The fields of ``config``'s MLflow dataset (``name``, ``digest``,
    ``source_type``, ``source``, ``profile``), or ``{}`` when its data cannot
    be read (the run itself then fails and says why): a name for the UI
    never costs a run its record."""
    try:
        if config["pipeline"] == "tracks":
            return _tracks(config)
        return _shape(config)
    except Exception:  # noqa: BLE001  (a plug-in's data set may raise anything)
        return {}


def _tracks(config: RunConfig) -> dict[str, str]:
    from mpe3d.harness.userdata.formats import content_digest

    path = track_file(config.values, "tracks.path")
    return {"name": path.name, "digest": _short(content_digest(path)), "source_type": "local",
            "source": str(path.resolve()), "profile": json.dumps({"kind": "keypoint tracks"})}


def _shape(config: RunConfig) -> dict[str, str]:
    # here, not at the top: the parent process, which imports this module to
    # record a run whose worker died, need not load trimesh (0.5 s) for it
    from mpe3d.harness.scene import shapes
    from mpe3d.harness.userdata.formats import content_digest

    spec = config["shape"]
    mesh = shapes.mesh_file(spec)
    source_type, source, data = ("code", f"mpe3d:{spec}", f"shape:{spec}") if mesh is None \
        else ("local", str(mesh.resolve()), content_digest(mesh))
    if config["pipeline"] == "colmap":
        sampling = {"photos": config["images.count"], "size_px": config["images.size"]}
        name = f"{spec} photos"
    else:
        sampling = {"points": config["points"], "sampling": "area-uniform"}
        name = spec
    digest = _short(json.dumps({"data": data, **sampling}, sort_keys=True))
    return {"name": name, "digest": digest, "source_type": source_type, "source": source,
            "profile": json.dumps(sampling, sort_keys=True)}


def _short(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:DIGEST_CHARS]

