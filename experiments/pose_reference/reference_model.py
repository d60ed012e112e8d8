"""A COLMAP dataset at a capture's published reference poses, with 3D points triangulated from an
eg-process database of the same photos: the reference to train on beside eg-process's own model
(the same images, the same test views, only the poses and points differ).

    python experiments/pose_reference/reference_model.py POSED REFERENCE_POSES OUT [--names-from ALL_IMAGES]

POSED is an eg-process output (its images/ and database.db are read, never written); the
reference is an LLFF poses_bounds.npy (rows in name order of --names-from, with [H, W, focal] of
the full-size images: the focal is rescaled to POSED's images) or a COLMAP model. OUT gets
images/ (links to POSED's) and sparse/0.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import pycolmap

from exploregs_plugin.bench.components.pose_agreement import colmap_cameras, llff_cameras


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("posed", type=Path)
    parser.add_argument("reference", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--names-from", type=Path)
    args = parser.parse_args()
    images = args.posed / "images"
    if args.reference.suffix == ".npy":
        names = sorted(p.name for p in args.names_from.iterdir() if p.is_file())
        poses = llff_cameras(args.reference, names)
        h, w, f = np.load(args.reference)[0, :15].reshape(3, 5)[:, 4]
        from PIL import Image

        with Image.open(next(images.iterdir())) as im:
            width, height = im.size
        focal = f * width / w
        camera = pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.PINHOLE, focal, width, height)
        camera.params = [focal, focal * height / h * w / width, width / 2.0, height / 2.0]
    else:
        poses = colmap_cameras(args.reference)
        camera = next(iter(pycolmap.Reconstruction(str(args.reference)).cameras.values()))
        camera.camera_id = 1
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    with pycolmap.Database.open(args.posed / "database.db") as db:
        for image in db.read_all_images():
            if image.name not in poses:
                continue
            w2c = np.linalg.inv(poses[image.name])
            new = pycolmap.Image(name=image.name, camera_id=1, image_id=image.image_id)
            new.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in db.read_keypoints(image.image_id)[:, :2].astype(np.float64)])
            rec.add_image_with_trivial_frame(new, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    if not (args.out / "images").exists():
        shutil.copytree(images, args.out / "images")
    work = args.out / "triangulation"
    work.mkdir(exist_ok=True)
    shutil.copyfile(args.posed / "database.db", work / "database.db")
    with pycolmap.Database.open(work / "database.db") as db:  # the copy's cameras become the reference's
        for cam in db.read_all_cameras():
            camera.camera_id = cam.camera_id
            db.update_camera(camera)
    result = pycolmap.triangulate_points(rec, work / "database.db", images, work / "model")
    result.write(str(args.out / "sparse" / "0"))
    shutil.rmtree(work)
    print(f"{args.out}: {result.num_reg_images()} images at the reference poses, {result.num_points3D()} points, "
          f"mean reprojection error {result.compute_mean_reprojection_error():.2f} px")


if __name__ == "__main__":
    main()
