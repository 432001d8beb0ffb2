"""deploy.io: the OpenCV cameras (frame conversion, a recorded video replayed, the reader thread's shutdown) and the simulated world."""

import queue
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from conftest import ROOT, refusal
from deploy import io
from envs.car_interface import FRAME_SHAPE


def write_video(path, levels, size=(160, 120)) -> str:
    """An MJPG video whose frame i is uniformly grey at levels[i]."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20, size)
    assert writer.isOpened()
    for level in levels:
        writer.write(np.full((size[1], size[0], 3), level, dtype=np.uint8))
    writer.release()
    return str(path)


def test_a_recorded_video_is_replayed_frame_by_frame_at_the_policys_size(tmp_path):
    levels = [0, 60, 120, 180, 240]
    camera = io.open_camera(f"file:{write_video(tmp_path / 'drive.avi', levels)}")
    for level in levels:
        frame, captured = camera.read()
        assert frame.shape == FRAME_SHAPE and frame.dtype == np.uint8
        assert abs(frame.mean() - level) < 4  # JPEG's loss, nothing more
        assert abs(captured - time.monotonic()) < 1.0
    assert camera.read() == (None, 0.0)  # the video ended: no frame, which the control loop counts as stale
    assert camera.frames_read == len(levels)
    camera.close()


def test_the_reader_thread_keeps_the_newest_frame_and_is_joined_before_the_capture_is_released(tmp_path):
    camera = io.OpenCVCamera(write_video(tmp_path / "drive.avi", [10, 100, 200]))  # realtime: a thread reads
    deadline = time.monotonic() + 10
    while camera.frames_read < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    frame, _ = camera.read()
    assert camera.frames_read == 3 and abs(frame.mean() - 200) < 4  # the newest of the three
    camera.close()
    assert not camera._thread.is_alive()


class ScriptedCapture:
    """A capture whose first frame is ready at open, then whose reads answer what the test puts in ``reads``."""

    def __init__(self, *args):
        self.reads = queue.Queue()
        self.first = True

    def isOpened(self):
        return True

    def read(self):
        if self.first:
            self.first = False
            return True, np.full((120, 160, 3), 10, dtype=np.uint8)
        level = self.reads.get(timeout=10)
        return (False, None) if level is None else (True, np.full((120, 160, 3), level, dtype=np.uint8))

    def release(self):
        pass


def test_a_live_camera_has_its_first_frame_at_open_and_reads_on_after_a_missed_frame(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", ScriptedCapture)
    camera = io.open_camera("usb:0")
    frame, captured = camera.read()  # before the reader thread has read anything: the frame read at open
    assert frame is not None and frame.mean() == 10 and camera.frames_read == 1 and captured > 0
    for level in (None, None, 100):  # two reads that deliver nothing, as a USB camera may, then a frame
        camera.capture.reads.put(level)
    deadline = time.monotonic() + 10
    while camera.frames_read < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert camera.frames_read == 2 and camera.read()[0].mean() == 100
    camera.capture.reads.put(None)  # lets the reader's last read return, so that close() can join it
    camera.close()
    assert not camera._thread.is_alive()


def test_a_live_camera_whose_first_frame_is_late_opens_and_a_video_without_one_is_refused(monkeypatch):
    released = []

    class Starting(ScriptedCapture):  # no frame at the first read, as a camera that is still starting
        def read(self):
            if self.first:
                self.first = False
                return False, None
            return super().read()

        def release(self):
            released.append(self)

    monkeypatch.setattr(cv2, "VideoCapture", Starting)
    camera = io.open_camera("usb:0")
    assert camera.read() == (None, 0.0) and camera.frames_read == 0  # stale until the reader has a frame
    camera.capture.reads.put(100)
    deadline = time.monotonic() + 10
    while camera.frames_read < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert camera.read()[0].mean() == 100
    camera.capture.reads.put(None)  # lets the reader's last read return, so that close() can join it
    camera.close()
    with pytest.raises(ValueError, match=r"^camera 'drive.avi' gave no frame: an empty video, or one in a codec this OpenCV cannot decode$"):
        io.open_camera("file:drive.avi")  # the same capture, read as a video: no first frame is none at all
    assert len(released) == 2 and released[0] is camera.capture  # the refused video's capture released too


def test_opencvs_build_information_tells_whether_it_opens_gstreamer_pipelines():
    assert io.has_gstreamer("  Video I/O:\n    FFMPEG:                      YES\n    GStreamer:                   YES (1.16.3)\n")  # JetPack's
    assert not io.has_gstreamer("  Video I/O:\n    FFMPEG:                      YES\n    GStreamer:                   NO\n")  # PyPI's wheels
    assert io.has_gstreamer("  Video I/O:\n    FFMPEG:                      YES\n")  # a build that does not say: let the pipeline try


def test_the_csi_camera_needs_an_opencv_built_with_gstreamer(monkeypatch):
    """PyPI's opencv-python wheels have no GStreamer, so the CSI pipeline cannot open through them: that is said,
    with what to use instead, rather than only "cannot open camera" with the pipeline."""
    monkeypatch.setattr(cv2, "getBuildInformation", lambda: "  Video I/O:\n    GStreamer:                   NO\n")
    opened = []
    monkeypatch.setattr(cv2, "VideoCapture", lambda *args: opened.append(args))
    with pytest.raises(ValueError, match=r"^camera 'csi' needs OpenCV built with GStreamer, which this OpenCV \S+ is not \(PyPI's opencv-python wheels"
                                         r" never are\): on the Jetson use JetPack's OpenCV, or a USB camera \(--camera usb:0\)$"):
        io.open_camera("csi")
    assert opened == [], "refused before a capture is made"


def test_the_csi_camera_opens_the_jetsons_gstreamer_pipeline_at_the_policys_frame_size(monkeypatch):
    monkeypatch.setattr(cv2, "getBuildInformation", lambda: "  Video I/O:\n    GStreamer:                   YES (1.16.3)\n")  # as on the Jetson
    with pytest.raises(ValueError, match=r"^cannot open camera 'nvarguscamerasrc ! "):  # but no camera here: one line naming the pipeline
        io.open_camera("csi")
    opened = []

    class Recorded(ScriptedCapture):
        def __init__(self, *args):
            super().__init__()
            opened.append(args)

    monkeypatch.setattr(cv2, "VideoCapture", Recorded)
    camera = io.open_camera("csi")
    try:
        ((pipeline, api),) = opened
        assert api == cv2.CAP_GSTREAMER
        elements = [element.strip() for element in pipeline.split("!")]
        assert elements[0] == "nvarguscamerasrc" and elements[-1] == "appsink drop=true max-buffers=1"  # the newest frame, none queued
        assert f"video/x-raw, width={FRAME_SHAPE[1]}, height={FRAME_SHAPE[0]}, format=BGRx" in elements  # scaled by nvvidconv, on the GPU
        assert elements[-2] == "video/x-raw, format=BGR" and camera.read()[0].shape == FRAME_SHAPE
    finally:
        camera.capture.reads.put(None)  # lets the reader's read return, so that close() can join it
        camera.close()


def test_a_usb_camera_that_does_not_open_says_whether_linux_has_it_and_lets_the_user_open_it(monkeypatch):
    """OpenCV says only that it could not open camera N; on Linux its /dev/videoN says why: missing, or not open to
    the user, whose remedy is the video group. A device the user may open adds nothing, nor do a file and another OS."""
    modes = []

    class Unopened:
        def __init__(self, *args):
            pass

        def isOpened(self):
            return False

    monkeypatch.setattr(cv2, "VideoCapture", Unopened)
    nodes = {"/dev/video0": True, "/dev/video1": False}  # /dev/video2 is missing
    monkeypatch.setattr(io.os.path, "exists", lambda path: path in nodes)
    monkeypatch.setattr(io.os, "access", lambda path, mode: modes.append(mode) or nodes[path])
    assert refusal(io.open_camera, "usb:2") == "cannot open camera 2: there is no /dev/video2 (`ls /dev/video*` lists the cameras Linux sees)"
    assert refusal(io.open_camera, "usb:1") == ("cannot open camera 1: the user may not open /dev/video1 (on Linux: sudo usermod -aG video $USER,"
                                                 " then log in again)")
    assert modes == [io.os.R_OK | io.os.W_OK], "V4L2 opens the device read-write"
    assert refusal(io.open_camera, "usb:0") == "cannot open camera 0"  # there and open to the user: nothing the OS can add
    assert refusal(io.open_camera, "file:video2") == "cannot open camera 'video2'", "a file is no device"
    assert io.video_device_hint(2, platform="darwin") == "" and io.video_device_hint(2, platform="win32") == ""


def test_the_simulated_camera_needs_the_simulated_car():
    with pytest.raises(ValueError, match="camera 'sim' needs the simulator: use it with --port mockjetracer://"):
        io.open_camera("sim")


def test_frames_become_three_channel_bgr_at_the_policys_size():
    grey = np.tile(np.arange(160, dtype=np.uint8), (120, 1))
    frame = io.to_policy_frame(grey)
    expected = cv2.resize(grey, (FRAME_SHAPE[1], FRAME_SHAPE[0]), interpolation=cv2.INTER_AREA)
    assert frame.shape == FRAME_SHAPE and all(np.array_equal(frame[..., c], expected) for c in range(3))
    bgra = np.zeros((112, 112, 4), dtype=np.uint8)
    bgra[..., 0], bgra[..., 3] = 50, 255
    assert np.array_equal(io.to_policy_frame(bgra), np.stack([np.full((112, 112), v, np.uint8) for v in (50, 0, 0)], axis=2))
    assert np.array_equal(io.to_policy_frame(grey[..., None]), frame)  # grey with a channel axis of one
    for bad in (np.zeros((112, 112, 3), np.uint16), np.zeros((112, 112, 2), np.uint8), np.zeros(5, np.uint8)):
        with pytest.raises(ValueError, match="expected 8-bit grey, BGR or BGRA"):
            io.to_policy_frame(bad)


def test_a_camera_whose_frames_the_policy_cannot_use_is_refused_at_open(monkeypatch):
    released = []

    class DepthCamera:  # 16-bit frames, as a depth camera delivers
        def __init__(self, *args):
            pass

        def isOpened(self):
            return True

        def read(self):
            return True, np.zeros((480, 640), dtype=np.uint16)

        def release(self):
            released.append(True)

    monkeypatch.setattr(cv2, "VideoCapture", DepthCamera)
    with pytest.raises(ValueError, match=r"^camera 4 delivered a \(480, 640\) uint16 frame; expected 8-bit grey, BGR or BGRA$"):
        io.open_camera("usb:4")
    assert released == [True]


class ChangingCamera:
    """A capture whose first `good` frames are BGR, after which it fails as `then` says."""

    def __init__(self, good: int, then: str):
        self.good, self.then, self.reads = good, then, 0

    def isOpened(self):
        return True

    def read(self):
        self.reads += 1
        if self.reads <= self.good:
            return True, np.zeros((120, 160, 3), dtype=np.uint8)
        if self.then == "depth":  # the format changed mid-run: 16-bit frames
            return True, np.zeros((480, 640), dtype=np.uint16)
        raise cv2.error("driver crashed")

    def release(self):
        pass


@pytest.mark.parametrize("then, message", [
    ("depth", r"^camera 4 delivered a \(480, 640\) uint16 frame; expected 8-bit grey, BGR or BGRA$"),
    ("crash", r"^camera 4 failed \(error: driver crashed\)$"),
])  # fmt: skip
def test_a_camera_that_fails_after_it_opened_says_why_at_every_read(monkeypatch, then, message):
    monkeypatch.setattr(cv2, "VideoCapture", lambda *args: ChangingCamera(3, then))
    camera = io.open_camera("usb:4")
    deadline = time.monotonic() + 10
    while camera._thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not camera._thread.is_alive() and camera.frames_read == 3  # the reader ended at the bad frame
    for _ in range(2):  # not a stale frame the loop would wait on for seconds, nor a traceback in the reader
        with pytest.raises(io.CameraFailed, match=message):
            camera.read()
    camera.close()


def test_a_recorded_video_whose_format_changes_raises_camera_failed(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", lambda *args: ChangingCamera(2, "depth"))
    camera = io.open_camera("file:drive.avi")
    assert camera.read()[0].shape == FRAME_SHAPE and camera.read()[0].shape == FRAME_SHAPE
    with pytest.raises(io.CameraFailed, match=r"^camera 'drive.avi' delivered a \(480, 640\) uint16 frame"):
        camera.read()
    assert camera.frames_read == 2


def test_the_simulated_worlds_lap_times_survive_a_lane_departure():
    class Controller:  # what a mock controller applies: here a centre-line follower reading the simulator's truth
        steering, throttle = 0.0, 0.6

    controller = Controller()
    world = io.SimWorld(controller, seed=3)
    try:

        def follow(ticks: int) -> None:
            for _ in range(ticks):
                info = world.info
                controller.steering = float(np.clip(-4.0 * info["cte"] - 1.5 * info["heading_error"], -1.0, 1.0))
                world.tick()
                assert not world.off_track

        follow(700)
        before = world.lap_times
        assert len(before) == 3 and before == world.info["lap_times"]
        controller.steering = 1.0  # full lock: the car leaves the lane and the world puts it back
        for _ in range(40):
            world.tick()
            if world.off_track:
                break
        assert world.off_track and world.resets == 1 and world.info["lap_times"] == []
        assert world.lap_times == before  # the env forgot them; the world did not
        follow(800)
        assert len(world.lap_times) > len(before) and world.lap_times[: len(before)] == before
    finally:
        world.close()


def test_the_car_code_imports_where_there_is_no_fcntl():
    # Windows has no fcntl or termios; sim-in-the-loop training there needs neither (the gamepad is
    # Linux's joystick device, and the training lock takes msvcrt), so importing them must wait
    code = "import sys; sys.modules['fcntl'] = sys.modules['termios'] = None; import deploy.jetracer; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout == "ok\n", out.stderr
