"""A run's MLflow params are the keys its pipeline reads
(:data:`~mpe3d.harness.experiment.execute.PIPELINE_KEYS`): each pipeline, run
under a config that records every key it reads, reads no other."""

from __future__ import annotations

import dataclasses

import pytest

from mpe3d.errors import MpeError
from mpe3d.harness.experiment import execute
from mpe3d.harness.experiment.config import KEYS, PIPELINE_NAMES, make_config
from tests.helpers import scaled_track_set


class _Recorded(dict):
    """A config's values that note every key asked for."""

    def __init__(self, values, read: set[str]):
        super().__init__(values)
        self.read = read

    def __getitem__(self, key):
        self.read.add(key)
        return super().__getitem__(key)

    def get(self, key, default=None):
        self.read.add(key)
        return super().get(key, default)


def _declared(pipeline: str, key: str) -> bool:
    reads = execute.PIPELINE_KEYS[pipeline]
    return key in reads or key.startswith(tuple(r for r in reads if r.endswith(".")))


def _keys_read(config) -> set[str]:
    read: set[str] = set()
    try:
        execute.run(dataclasses.replace(config, values=_Recorded(config.values, read)))
    except MpeError:  # a method's refusal still read what it read
        pass
    return read


@pytest.mark.parametrize("pipeline", ["points", "tracks", "colmap"])
def test_a_pipeline_reads_only_the_keys_it_declares(tmp_path, pipeline):
    keys = {"points": {"shape": "torus", "points": 96, "views": 3, "visibility.mode": "count",
                       "noise.type": "distance", "noise.fraction": 0.1, "solver.name": "refine"},
            "tracks": {"pipeline": "tracks", "tracks.root": str(tmp_path), "tracks.path": "keypoints.csv",
                       "tracks.truth": "points.csv", "tracks.noise_px": 0.5, "tracks.drop_fraction": 0.1},
            "colmap": {"pipeline": "colmap", "shape": "torus", "points": 256, "images.count": 6,
                       "images.size": 96}}[pipeline]
    if pipeline == "tracks":
        scaled_track_set(tmp_path)
    config = make_config(keys)
    read = _keys_read(config)
    assert "pipeline" in read or pipeline == "points"
    assert {key for key in read if not _declared(pipeline, key)} == set()
    logged = execute.shaping_params(config)
    assert all(value is not None for value in logged.values())
    assert {key for key in read if config.flat().get(key) is not None} <= set(logged)
    others = {"points": ("tracks.", "images."), "tracks": ("visibility.", "noise.", "images.", "views"),
              "colmap": ("tracks.", "visibility.", "noise.", "solver.", "views")}[pipeline]
    assert not [key for key in logged if key.startswith(others)]  # another pipeline's keys
    if pipeline == "tracks":  # its solvers take no option: solver.name alone
        assert [key for key in logged if key.startswith("solver.")] == ["solver.name"]


def test_every_declared_key_is_a_key():
    assert set(execute.PIPELINE_KEYS) == set(PIPELINE_NAMES)
    for reads in execute.PIPELINE_KEYS.values():
        for name in reads:
            assert name in KEYS or any(key.startswith(name) for key in KEYS), name


def test_a_runs_data_set_names_its_data_and_mlflow_reads_its_source(tmp_path):
    """Runs on the same data share a digest, on other data (another sampling,
    another mesh's bytes, another keypoint file) they do not; a mesh file is
    named by its file name, a keypoint file as the sweep names it; MLflow
    reads the source back."""
    from mlflow.data.dataset_source_registry import get_dataset_source_from_json

    from mpe3d.harness.experiment.datasets import dataset_of

    torus = dataset_of(make_config({"shape": "torus", "points": 64}))
    assert torus == dataset_of(make_config({"shape": "torus", "points": 64, "views": 7, "seed": 3}))
    assert torus["digest"] != dataset_of(make_config({"shape": "torus", "points": 128}))["digest"]
    chair = dataset_of(make_config({"shape": "chair"}))
    mesh = tmp_path / "my chair.ply"
    mesh.write_bytes(__import__("mpe3d.harness.scene.shapes", fromlist=["x"]).mesh_file("chair").read_bytes())
    mine = dataset_of(make_config({"shape": str(mesh)}))
    assert mine["name"] == "my chair.ply" and mine["digest"] == chair["digest"]  # the same bytes
    assert dataset_of(make_config({"pipeline": "colmap", "shape": "chair"}))["name"] == "chair photos"
    for seed, name in enumerate(("house", "dino")):  # two data sets, each a keypoints.csv
        scaled_track_set(tmp_path / name, seed=seed)
    house, dino = (dataset_of(make_config({"pipeline": "tracks", "tracks.root": str(tmp_path),
                                           "tracks.path": f"{name}/keypoints.csv"}))
                   for name in ("house", "dino"))
    assert house["name"] == "house/keypoints.csv" and house["digest"] != dino["digest"]
    for fields in (torus, mine, house):
        source = get_dataset_source_from_json(fields["source"], fields["source_type"])
        assert source.to_json() == fields["source"]
    assert dataset_of(make_config({"shape": str(tmp_path / "gone.ply")})) == {}  # the run will say why
