"""Rebuild the bundled stand-in meshes in ``harness/scene/assets/meshes``.

The paper evaluates on ShapeNet and Pix3D, which cannot be redistributed. We
ship one CC0 mesh per paper category instead, taken from the BlendSwap-CC-0
furniture library (Debian's ``sweethome3d-furniture`` 1.8) that sits in
``../shared/meshes/cc0``. Each mesh is decimated to a few thousand faces so the
wheel stays small and ray casting stays fast, then written as binary PLY next
to ``manifest.json`` (name, paper category, source file, creator, face counts)
and ``CREDITS.md``.

Run from the repository root::

    python scripts/build_bundled_meshes.py [--source ../shared/meshes/cc0]

Needs ``fast-simplification`` (trimesh's quadric decimation backend), which is
a build-time tool only and not a runtime dependency.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import trimesh

# name -> (source file, paper category, why this one)
CHOICES = {
    "airplane": ("cartoon_biplane.ply", "airplane", "the only aircraft in the library"),
    "bench": ("bench.ply", "bench", "a plain outdoor bench"),
    "car": ("peterbilt.ply", "car", "a truck: the closest road vehicle to a car"),
    "chair": ("chair.ply", "chair", "a four-legged dining chair"),
    "lamp": ("desklamp.ply", "lamp", "an articulated desk lamp"),
    "sofa": ("sofa2.ply", "sofa", "a three-seat sofa"),
    "table": ("table.ply", "table", "a four-legged table"),
    "guitar": ("electricGuitar.ply", "rifle", "long and thin, standing in for ShapeNet's rifle"),
}
TARGET_FACES = 4000


def build(source: Path, out: Path) -> list[dict]:
    catalog = {e["file"]: e for e in json.loads((source / "catalog.json").read_text())}
    manifest = []
    for name, (file, category, why) in CHOICES.items():
        mesh = trimesh.load(source / file, force="mesh", process=True)
        original_faces = len(mesh.faces)
        if original_faces > TARGET_FACES:
            mesh = mesh.simplify_quadric_decimation(face_count=TARGET_FACES)
        mesh.remove_unreferenced_vertices()
        mesh.export(out / f"{name}.ply", encoding="binary")
        entry = catalog[file]
        manifest.append({
            "name": name, "paper_category": category, "why": why,
            "source_file": file, "source_name": entry["name"],
            "creator": entry["creator"], "license": entry["license"],
            "source": entry["source"], "original_faces": original_faces,
            "faces": len(mesh.faces), "vertices": len(mesh.vertices),
        })
    return manifest


def write_credits(manifest: list[dict], out: Path) -> None:
    lines = [
        "# Credits for the bundled meshes",
        "",
        "These meshes come from the BlendSwap-CC-0 furniture library, as packaged in",
        "Debian's `sweethome3d-furniture` 1.8. The library is released under CC0 1.0",
        "(public domain dedication); we credit the creators as a courtesy. Each mesh",
        "was decimated with trimesh's quadric decimation by",
        "`scripts/build_bundled_meshes.py`.",
        "",
        "| name | stands in for | original | creator | faces (original → bundled) |",
        "|---|---|---|---|---|",
    ]
    for m in manifest:
        lines.append(
            f"| {m['name']} | {m['paper_category']} | {m['source_name']} (`{m['source_file']}`) "
            f"| {m['creator']} | {m['original_faces']} → {m['faces']} |")
    (out / "CREDITS.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=Path("../shared/meshes/cc0"))
    parser.add_argument("--out", type=Path, default=Path("harness/scene/assets/meshes"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    manifest = build(args.source, args.out)
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    write_credits(manifest, args.out)
    for m in manifest:
        print(f"{m['name']:>9}: {m['original_faces']:>6} -> {m['faces']:>5} faces")


if __name__ == "__main__":
    main()
