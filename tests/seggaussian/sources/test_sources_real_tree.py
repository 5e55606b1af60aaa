"""The readers on complete generated trees: ScanNet++ v2 (distorted download + undistortion output) and
Replica (official release folder + NICE-SLAM renders).

The names checked here come from the ScanNet++ toolkit (``common/scene_release.py``,
``dslr/configs/undistort.yml``) and the Replica-Dataset README / NICE-SLAM download, not from our
readers: the generators must write what a real download holds, and the readers must read such a tree.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from seggaussian.pipeline.dataset import build_dataset
from seggaussian import shards
from seggaussian.pipeline.config import BuildConfig
from seggaussian.labels.config import OracleConfig
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.fit.views import load_views, masked_render
from seggaussian.fit.losses import fitting_loss
from seggaussian.sources import replica, scannetpp
from seggaussian.sources.synthetic import scannetpp as synth_scannetpp
from seggaussian.sources.synthetic import generate as synthetic
from seggaussian.sources._common import SourceError, atomic_write_image, read_image, read_valid_mask

SMALL = synthetic.SynthConfig(width=48, num_views=6, max_edge=0.2)

#: Every path of a ScanNet++ v2 scene (toolkit ``ScannetppScene_Release`` properties and the
#: undistortion config's outputs), relative to ``data/<scene_id>/``; folders end with "/".
RELEASE_SCENE_PATHS = (
    "scans/mesh_aligned_0.05.ply", "scans/mesh_aligned_0.05_mask.txt", "scans/mesh_aligned_0.05_semantic.ply",
    "scans/segments.json", "scans/segments_anno.json", "scans/pc_aligned.ply", "scans/pc_aligned_mask.txt",
    "scans/scanner_poses.json",
    "dslr/resized_images/", "dslr/resized_anon_masks/", "dslr/original_images/", "dslr/original_anon_masks/",
    "dslr/resized_undistorted_images/", "dslr/resized_undistorted_masks/", "dslr/colmap/",
    "dslr/nerfstudio/transforms.json", "dslr/nerfstudio/transforms_undistorted.json", "dslr/train_test_lists.json",
    "dslr/undistorted_images/", "dslr/undistorted_anon_masks/",
    "iphone/rgb.mkv", "iphone/rgb_mask.mkv", "iphone/depth.bin", "iphone/pose_intrinsic_imu.json",
    "iphone/colmap/", "iphone/nerfstudio/transforms.json", "iphone/exif.json",
    "panocam/images/", "panocam/anon_mask/", "panocam/depth/", "panocam/azim/", "panocam/elev/",
    "panocam/resized_images/", "panocam/resized_depth/", "panocam/resized_anon_mask/", "panocam/resized_azim/",
    "panocam/resized_elev/",
)
#: An official Replica scene folder (Replica-Dataset README "Dataset Layout") plus NICE-SLAM's renders.
REPLICA_ROOM_PATHS = (
    "glass.sur", "mesh.ply", "preseg.bin", "preseg.json", "semantic.bin", "semantic.json", "textures/parameters.json",
    "textures/0-color-ptex.hdr", "textures/0-color-ptex.w", "habitat/mesh_semantic.ply", "habitat/mesh_semantic.navmesh",
    "habitat/info_semantic.json", "habitat/mesh_preseg_semantic.ply", "habitat/mesh_preseg_semantic.navmesh",
    "habitat/info_preseg_semantic.json", "traj.txt", "results/frame000000.jpg", "results/depth000000.png",
)
RELEASE_ROOT_PATHS = ("metadata/semantic_benchmark/map_benchmark.csv", "metadata/semantic_classes.txt",
                      "metadata/instance_classes.txt", "splits/nvs_sem_train.txt", "splits/nvs_sem_val.txt")


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("spp")
    (scene_id,) = synthetic.synthesize(root, 1, 3, "scannetpp", SMALL)
    return root, scene_id


@pytest.fixture
def tree(pristine, tmp_path):
    root, scene_id = pristine
    shutil.copytree(root, tmp_path / "spp")
    return tmp_path / "spp", scene_id, tmp_path / "spp" / "data" / scene_id


def test_generator_writes_every_path_of_a_release_scene(pristine):
    root, scene_id = pristine
    scene_dir = root / "data" / scene_id
    for rel in RELEASE_SCENE_PATHS:
        path = scene_dir / rel.rstrip("/")
        if rel.endswith("/"):
            assert path.is_dir() and any(path.iterdir()), rel
        else:
            assert path.is_file() and path.stat().st_size > 0, rel
    for rel in RELEASE_ROOT_PATHS:
        assert (root / rel).is_file(), rel
    # distorted data: a fisheye camera with other intrinsics than the undistorted pinhole one
    distorted = json.loads((scene_dir / scannetpp.DISTORTED_TRANSFORMS_FILE).read_text())
    undistorted = json.loads((scene_dir / scannetpp.TRANSFORMS_FILE).read_text())
    assert distorted["camera_model"] == "OPENCV_FISHEYE" and undistorted["camera_model"] == "PINHOLE"
    assert distorted["fl_x"] != undistorted["fl_x"] and distorted["k1"] != 0.0
    assert "OPENCV_FISHEYE" in (scene_dir / scannetpp.COLMAP_CAMERAS_FILE).read_text()
    # every frame names its mask (toolkit field mask_path) and the mask exists in every mask folder
    for frame in undistorted["frames"] + undistorted["test_frames"]:
        for folder in ("resized_anon_masks", "undistorted_anon_masks", "resized_undistorted_masks"):
            assert (scene_dir / "dslr" / folder / frame["mask_path"]).is_file()


def test_reader_uses_undistorted_data_and_ignores_the_rest(pristine):
    root, scene_id = pristine
    scene = scannetpp.read_scene(root, scene_id)
    scene_dir = root / "data" / scene_id
    undistorted = json.loads((scene_dir / scannetpp.TRANSFORMS_FILE).read_text())
    distorted = json.loads((scene_dir / scannetpp.DISTORTED_TRANSFORMS_FILE).read_text())
    colmap = scannetpp.read_colmap_images(scene_dir / scannetpp.COLMAP_IMAGES_FILE)
    assert len(scene.views) == SMALL.num_views
    for view in scene.views:
        K = view.camera.K
        assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == pytest.approx(
            (undistorted["fl_x"], undistorted["fl_y"], undistorted["cx"], undistorted["cy"]))
        assert K[0, 0] != pytest.approx(distorted["fl_x"])
        np.testing.assert_allclose(view.camera.viewmat, colmap[view.name], atol=1e-12)
        assert view.image_path.parent.name == "undistorted_images"
        assert view.mask_path is not None and view.mask_path.parent.name == "undistorted_anon_masks"
    assert scene.stats["pose_disagreements"] == 0 and scene.stats["anon_masks"] == SMALL.num_views


def test_resized_undistorted_folders_are_the_fallback(tree):
    root, scene_id, scene_dir = tree
    shutil.rmtree(scene_dir / "dslr/undistorted_images")
    shutil.rmtree(scene_dir / "dslr/undistorted_anon_masks")
    scene = scannetpp.read_scene(root, scene_id)
    assert {v.image_path.parent.name for v in scene.views} == {"resized_undistorted_images"}
    assert {v.mask_path.parent.name for v in scene.views} == {"resized_undistorted_masks"}


def test_without_undistorted_data_the_error_names_the_toolkit_command(tree):
    root, scene_id, scene_dir = tree
    (scene_dir / scannetpp.TRANSFORMS_FILE).unlink()
    shutil.rmtree(scene_dir / "dslr/undistorted_images")
    with pytest.raises(SourceError) as info:
        scannetpp.read_scene(root, scene_id)
    message = str(info.value)
    assert "transforms_undistorted.json" in message and "OPENCV_FISHEYE" in message
    assert scannetpp.UNDISTORT_COMMAND in message and "python -m dslr.undistort dslr/configs/undistort.yml" in message
    assert "\n" not in message


def test_empty_distorted_folder_alone_does_not_stop_the_reader(tree):
    root, scene_id, scene_dir = tree
    shutil.rmtree(scene_dir / "dslr/resized_images")
    (scene_dir / "dslr/resized_images").mkdir()  # the reported trigger: an empty resized_images/
    assert scannetpp.read_scene(root, scene_id).views


def test_missing_listed_mask_is_an_error(tree):
    root, scene_id, scene_dir = tree
    (scene_dir / "dslr/undistorted_anon_masks/DSC00002.png").unlink()
    with pytest.raises(SourceError, match="anonymization mask"):
        scannetpp.read_scene(root, scene_id)


def test_valid_mask_reads_the_toolkit_convention(tmp_path):
    mask = synth_scannetpp.anon_mask(1, 40, 30)
    assert (mask == 0).sum() > 0 and set(np.unique(mask)) == {0, 255}
    path = tmp_path / "m.png"
    atomic_write_image(path, mask)
    valid = read_valid_mask(path, 40, 30)
    np.testing.assert_array_equal(valid, mask == 255)
    half = read_valid_mask(path, 20, 15)  # resized view: a pixel touching the anonymized box is anonymized
    assert (~half).sum() >= (mask == 0).sum() / 4
    top, bottom, left, right = synth_scannetpp.anon_box(1, 40, 30)
    assert not half[top // 2:(bottom + 1) // 2, left // 2:(right + 1) // 2].any()
    with pytest.raises(SourceError, match="not a resize"):
        read_valid_mask(path, 40, 10)


def test_anonymized_pixels_carry_no_rgb_loss(pristine):
    root, scene_id = pristine
    scene = scannetpp.read_scene(root, scene_id)
    view = next(v for v in scene.views if v.name == synth_scannetpp.image_name(1))
    (data,) = load_views([view], 1.0)
    assert data.valid is not None and (~data.valid).sum() > 0
    render = torch.rand_like(data.image, requires_grad=True)
    loss = fitting_loss(masked_render(render, data), data.image, 0.2)
    loss.backward()
    grad = render.grad.abs().sum(-1)
    assert float(grad[~data.valid].max()) == 0.0 and float(grad[data.valid].min()) > 0.0
    # changing the render only on anonymized pixels leaves the loss unchanged
    other = render.detach().clone()
    other[~data.valid] = 0.0
    assert float(fitting_loss(masked_render(other, data), data.image, 0.2)) == pytest.approx(loss.item())


def test_build_succeeds_on_the_complete_tree_and_masks_label_maps(pristine, tmp_path):
    root, scene_id = pristine
    out = tmp_path / "dataset"
    config = BuildConfig(source="scannetpp", root=root, out=out, gaussians="oracle", progress=False,
                         oracle=OracleConfig(num_gaussians=3000))
    report = build_dataset(config)
    assert report.counts["built"] == 1 and report.counts["failed"] == 0
    # the transfer report of a generated room: a real (non-zero) median spacing of the mesh points
    transfer = report.outcomes[0].info["transfer"]
    assert 0.0 < transfer["spacing"] < config.transfer.mesh_sample_spacing
    assert transfer["gate"] == pytest.approx(max(config.transfer.gate_min, config.transfer.gate_factor * transfer["spacing"]))
    (split,) = [s for s in ("train", "val", "xval") if scene_id in shards.list_scenes(out, s)]
    record = shards.read_scene(out, split, scene_id)
    scene = scannetpp.read_scene(root, scene_id)
    by_name = {v.name: v for v in scene.views}
    masked_views = 0
    for stored in record.views:
        valid = read_valid_mask(by_name[stored.name].mask_path, stored.camera.width, stored.camera.height)
        if valid.all():
            continue
        masked_views += 1
        assert (stored.semantic[~valid] == IGNORE_LABEL).all() and (stored.instance[~valid] == IGNORE_LABEL).all()
        # the anonymized box lies on labelled surfaces (the mesh raycast labels most of it), so the
        # ignore there comes from the mask
        truth = read_image(by_name[stored.name].semantic_path, "ground truth", unchanged=True)
        assert truth.shape == valid.shape and (truth[~valid] != IGNORE_LABEL).mean() > 0.5
    assert masked_views >= 1


def test_replica_generator_writes_the_release_folder_and_the_reader_reads_it(tmp_path):
    (room,) = synthetic.synthesize(tmp_path, 1, 3, "replica", synthetic.SynthConfig(width=48, num_views=3, max_edge=0.2))
    for rel in REPLICA_ROOM_PATHS:
        assert (tmp_path / room / rel).is_file(), rel
    # NICE-SLAM's root files beside the room folders are not scenes
    assert (tmp_path / "cam_params.json").is_file() and (tmp_path / f"{room}_mesh.ply").is_file()
    assert replica.list_scenes(tmp_path) == [room]
    scene = replica.read_scene(tmp_path, room)
    assert len(scene.views) == 3 and scene.stats.get("views_source") != "none"
    assert (scene.semantic != IGNORE_LABEL).any()
