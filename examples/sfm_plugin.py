"""An SfM method of your own, as a plug-in: mpe3d's bundle adjustment with
the pinhole camera, run through the public API and its cameras handed back.

    mpe3d check-solver pinhole_bundle --plugin examples/sfm_plugin.py
    mpe3d sweep sweeps/photos.yaml photos.root=DIR --plugin examples/sfm_plugin.py --solver pinhole_bundle

Replace the body of ``pinhole_bundle`` with your own method: it is given each
photo's keypoints and track ids, size, EXIF focal length (or None) and camera
number, and returns the photos it registered and the points it placed.
"""

import numpy as np

import mpe3d
from mpe3d import SfmPose, SfmResult


@mpe3d.register_sfm("pinhole_bundle", summary="mpe3d.reconstruct's bundle adjustment, pinhole camera")
def pinhole_bundle(views, *, random_state):
    # Bundle adjustment has one principal point: every photo's keypoints are
    # moved round the first photo's centre, as if each were shot centred there.
    centres = [np.array(view.image_size, dtype=float) / 2 for view in views]
    several = len({view.camera for view in views}) > 1
    inputs = []
    for view, centre in zip(views, centres):
        offset = centre - centres[0]
        given = {"name": view.name, "ids": view.ids, "xy": view.xy - offset, "image_size": view.image_size}
        if several:  # a focal length fitted per camera
            given.update(camera=view.camera, offset=tuple(offset))
        elif view.focal_px is not None:
            given["focal_px"] = view.focal_px
        inputs.append(given)
    result = mpe3d.reconstruct(inputs, solver="bundle", camera="perspective", random_state=random_state,
                               principal_point=tuple(centres[0]))
    poses = {camera.view: SfmPose(rotation=camera.rotation, translation=camera.translation,
                                  focal_px=camera.focal_px, principal_point=tuple(centre))
             for camera, centre in zip(result.cameras, centres) if camera.registered}
    placed = np.all(np.isfinite(result.points), axis=1)
    return SfmResult(poses=poses, point_ids=np.asarray(result.ids)[placed], points=result.points[placed],
                     termination=str(result.report.get("termination", "")))
