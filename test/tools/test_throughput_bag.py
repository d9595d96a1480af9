"""scripts/throughput_bag.py, the bag of the end-to-end replay throughput (docs/tools.md): general_motion's frames
played back and forth as raw mono8, with their camera_info and ground truth, at 15 Hz."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from epi_vo.io import bagio
from epi_vo.io.msgconv import decode_frame

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "bags" / "general_motion" / "bag"


def _load(path: Path) -> tuple[list[np.ndarray], list[int], np.ndarray]:
    with bagio.open_camera_bag(path) as bag:
        frames = list(bag.iter_frames())
        images = [decode_frame(f.image_msg, bag.image_is_compressed) for f in frames]
        gt = bag.read_ground_truth()
    assert gt is not None
    return images, [f.stamp_ns for f in frames], gt.positions


def test_frames_play_back_and_forth_as_raw_mono8(tmp_path: Path) -> None:
    out = tmp_path / "tp"
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "throughput_bag.py"), str(out), "--frames", "110"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    src, _, src_gt = _load(SOURCE)
    images, stamps, gt = _load(out)
    assert len(images) == 110 and images[0].dtype == np.uint8 and images[0].shape == src[0].shape
    # 0..51, 50..1, 0..7: frame 52 is source frame 50, frame 102 source frame 0 again.
    cycle = list(range(52)) + list(range(50, 0, -1))
    for i in (0, 51, 52, 101, 102, 109):
        k = cycle[i % len(cycle)]
        assert np.array_equal(images[i], cv2.cvtColor(src[k], cv2.COLOR_BGR2GRAY) if src[k].ndim == 3 else src[k])
        assert np.allclose(gt[i], src_gt[k])
    assert np.all(np.diff(stamps) == 66_666_667)
