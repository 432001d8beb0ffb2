"""Cameras, the gamepad, and the simulated car for sim-in-the-loop runs. Runs on Python 3.8.

Every camera returns `(frame, timestamp)`: a 112x112 BGR uint8 frame (`envs.car_interface.FRAME_SHAPE`)
and the monotonic time it was captured, or `(None, 0.0)` when it has none; the control loop treats a
frame older than two control periods as lost. A camera that can deliver no usable frame again raises
CameraFailed, and the run ends at once. OpenCV and the simulator are imported lazily.
"""

from __future__ import annotations

import errno
import os
import re
import struct
import sys
import threading
import time
from typing import Any, Dict, List, Optional, Protocol, Tuple, Union

import numpy as np

from envs.car_interface import FRAME_SHAPE

Frame = Tuple[Optional[np.ndarray], float]


def csi_pipeline(width: int = FRAME_SHAPE[1], height: int = FRAME_SHAPE[0], fps: int = 30) -> str:
    """GStreamer pipeline for a Jetson CSI camera, scaled on the GPU to the policy's frame size (BGR)."""
    return (
        "nvarguscamerasrc ! video/x-raw(memory:NVMM), width=1280, height=720, framerate=%d/1 ! "
        "nvvidconv ! video/x-raw, width=%d, height=%d, format=BGRx ! videoconvert ! video/x-raw, format=BGR ! "
        "appsink drop=true max-buffers=1" % (fps, width, height)
    )


def has_gstreamer(build_information: str) -> bool:
    """Whether an OpenCV build (`cv2.getBuildInformation()`) opens GStreamer pipelines; True where it does not say.
    PyPI's opencv-python wheels are built without it, so a CSI camera can never open through them."""
    match = re.search(r"^\s*GStreamer:\s*(\S+)", build_information, re.M)
    return match is None or match.group(1).upper() != "NO"


def video_device_hint(index: int, platform: str = sys.platform) -> str:
    """Why OpenCV could not open USB camera `index`, where Linux can tell (OpenCV says only that it could not): its
    /dev/videoN is missing, or not open to the user, who on a Jetson must be in the video group; "" otherwise."""
    path = f"/dev/video{index}"
    if not platform.startswith("linux"):
        return ""
    if not os.path.exists(path):
        return f": there is no {path} (`ls /dev/video*` lists the cameras Linux sees)"
    if not os.access(path, os.R_OK | os.W_OK):  # V4L2 opens the device read-write
        return f": the user may not open {path} (on Linux: sudo usermod -aG video $USER, then log in again)"
    return ""


def to_policy_frame(frame: np.ndarray) -> np.ndarray:
    """A camera's frame as FRAME_SHAPE BGR uint8: grey and BGRA frames get three channels, other sizes are resized.

    ValueError for anything else (a 16-bit or 2-channel frame), which the control loop would misread.
    """
    import cv2

    frame = np.asarray(frame)
    if frame.dtype != np.uint8 or not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] in (1, 3, 4))):
        raise ValueError(f"a {frame.shape} {frame.dtype} frame; expected 8-bit grey, BGR or BGRA")
    if frame.ndim == 2 or frame.shape[2] == 1:
        frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    elif frame.shape[2] == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    if frame.shape != FRAME_SHAPE:
        frame = cv2.resize(frame, (FRAME_SHAPE[1], FRAME_SHAPE[0]), interpolation=cv2.INTER_AREA)
    return frame


class CameraFailed(Exception):
    """The camera delivered a frame the policy cannot use after it opened, or its reader failed."""


class OpenCVCamera:
    """A cv2.VideoCapture read by a background thread, so `read()` returns the newest frame at once.

    The first frame is read when the camera opens, so a format the policy cannot use is an error there,
    before the car is armed. Such a frame later on (or an error in the reader) makes every `read()`
    raise CameraFailed, naming it.
    """

    def __init__(self, source: Union[str, int], api: Optional[int] = None, realtime: bool = True) -> None:
        import cv2

        self.capture = cv2.VideoCapture(source, api) if api is not None else cv2.VideoCapture(source)
        if not self.capture.isOpened():  # a device number is a /dev/videoN, whose state may say why
            raise ValueError(f"cannot open camera {source!r}" + (video_device_hint(source) if isinstance(source, int) else ""))
        self.source = source
        self.realtime = realtime  # False for a video file: one new frame per read, at the file's pace
        self._failure: Optional[str] = None  # why the reader thread ended, for read() to raise
        self._latest: Frame = (None, 0.0)
        self._pending: Optional[np.ndarray] = None  # a video file's first frame, read at open
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.frames_read = 0
        ok, frame = self.capture.read()
        if not ok and not realtime:  # a live camera's first frame may come late; a video that gives none has none
            self.capture.release()
            raise ValueError(f"camera {source!r} gave no frame: an empty video, or one in a codec this OpenCV cannot decode")
        if ok:
            try:
                frame = to_policy_frame(frame)
            except ValueError as err:
                self.capture.release()
                raise ValueError(f"camera {source!r} delivered {err}") from None
            if realtime:
                self._latest = (frame, time.monotonic())
                self.frames_read = 1
            else:
                self._pending = frame
        if realtime:
            self._thread = threading.Thread(target=self._grab, daemon=True)
            self._thread.start()

    def _grab(self) -> None:
        while not self._stop.is_set():
            try:
                ok, frame = self.capture.read()
                if not ok:
                    time.sleep(0.005)
                    continue
                latest = (self._convert(frame), time.monotonic())
            except Exception as err:  # uncaught, the thread would die and the loop see only stale frames, never why
                self._failure = str(err) if isinstance(err, CameraFailed) else f"camera {self.source!r} failed ({type(err).__name__}: {err})"
                return
            with self._lock:
                self._latest = latest
                self.frames_read += 1

    def _convert(self, frame: np.ndarray) -> np.ndarray:
        try:
            return to_policy_frame(frame)
        except ValueError as err:  # the camera's format changed after it opened
            raise CameraFailed(f"camera {self.source!r} delivered {err}") from None

    def read(self) -> Frame:
        """The newest frame and its capture time; (None, 0.0) if none yet (or a video ended); CameraFailed."""
        if not self.realtime:
            frame, self._pending = self._pending, None
            if frame is None:
                ok, frame = self.capture.read()
                if not ok:
                    return None, 0.0
                frame = self._convert(frame)
            self.frames_read += 1
            return frame, time.monotonic()
        if self._failure is not None:
            raise CameraFailed(self._failure)
        with self._lock:
            return self._latest

    def close(self) -> None:
        self._stop.set()
        if self.realtime:
            self._thread.join(timeout=2.0)  # releasing the capture inside the thread's read() is undefined in OpenCV
        self.capture.release()


class AppliedOutputs(Protocol):
    """What the simulator reads of a motor controller: the outputs it applies now."""

    steering: float
    throttle: float


class SimWorld:
    """The PyBullet track car driven by a mock controller's applied outputs: sim-in-the-loop.

    `tick()` advances the car by one control period under whatever steering and throttle the
    controller is applying (so the serial protocol, the watchdog and STOP all act on the car), and
    `read()` is the car's camera. A car that leaves the lane is put back at a random pose.
    """

    def __init__(self, controller: AppliedOutputs, seed: int = 0, **env_kwargs: Any) -> None:
        from envs.jetracer_track import JetRacerTrackEnv

        self.controller = controller
        self.env = JetRacerTrackEnv(**env_kwargs)
        self.env.reset(seed=seed)
        self.seed, self.resets = seed, 0
        self.off_track = False
        self._laps_before_reset: List[float] = []  # the env forgets its lap times when it is reset

    def tick(self) -> float:
        """One control period; returns the centre-line progress in m."""
        progress, self.off_track = self.env.drive(self.controller.steering, self.controller.throttle)
        if self.off_track:
            self._laps_before_reset += self.info["lap_times"]
            self.resets += 1
            self.env.reset(seed=self.seed + self.resets)
        return progress

    @property
    def lap_times(self) -> List[float]:
        """Every lap completed since the world was made (simulated s), across the resets after lane departures."""
        return self._laps_before_reset + self.info["lap_times"]

    def read(self) -> Tuple[np.ndarray, float]:
        """The car's camera frame now, (112, 112, 3) uint8 BGR as OpenCV gives a real camera's, and the time it was taken."""
        return self.env.camera_frame_bgr(), time.monotonic()

    @property
    def info(self) -> dict:
        """The track env's info now: cross-track and heading error, speed, arc length, progress, laps and lap times."""
        return self.env._info()

    def close(self) -> None:
        self.env.close()


def open_camera(spec: str, world: Optional[SimWorld] = None) -> Union[OpenCVCamera, SimWorld]:
    """`csi`, `usb:N`, `file:PATH` (a recorded video, replayed frame by frame) or `sim`."""
    if spec == "sim":
        if world is None:
            raise ValueError("camera 'sim' needs the simulator: use it with --port mockjetracer://")
        return world
    if spec == "csi":
        import cv2

        if not has_gstreamer(cv2.getBuildInformation()):  # else only "cannot open camera" would say so
            raise ValueError(f"camera 'csi' needs OpenCV built with GStreamer, which this OpenCV {cv2.__version__} is not (PyPI's"
                             " opencv-python wheels never are): on the Jetson use JetPack's OpenCV, or a USB camera (--camera usb:0)")
        return OpenCVCamera(csi_pipeline(), cv2.CAP_GSTREAMER)
    if spec.startswith("usb:"):
        if not spec[4:].isdigit():
            raise ValueError(f"camera {spec!r}: usb:N takes a device number N")
        return OpenCVCamera(int(spec[4:]))
    if spec.startswith("file:"):
        return OpenCVCamera(spec[5:], realtime=False)
    raise ValueError(f"unknown camera {spec!r}: use csi, usb:N, file:PATH or sim")


class GamepadLost(Exception):
    """The gamepad stopped answering (unplugged, or a wireless one out of range): its e-stop is gone."""


# linux/joystick.h: _IOR('j', 0x11, __u8) and _IOR('j', 0x12, __u8), answered by joystick devices only
JSIOCGAXES, JSIOCGBUTTONS = 0x80016A11, 0x80016A12


def joystick_shape(fd: int) -> Optional[Tuple[int, int]]:
    """(axes, buttons) of the Linux joystick device open on fd; None if it is no joystick device."""
    import fcntl  # here, not at the top: Windows has none, and the simulated car needs no gamepad

    counts = []
    for request in (JSIOCGAXES, JSIOCGBUTTONS):
        count = bytearray(1)
        try:
            fcntl.ioctl(fd, request, count)
        except OSError:
            return None
        counts.append(count[0])
    return counts[0], counts[1]


class Gamepad:
    """A Linux joystick device (/dev/input/jsN) read without extra dependencies.

    Events are 8 bytes: time (ms, u32), value (i16), type (u8: 1 button, 2 axis, 0x80 initial state),
    number (u8). Axes are scaled to [-1, 1]. A read that ends inside an event keeps its start for the next.
    """

    EVENT = struct.Struct("<IhBB")

    def __init__(self, path: str) -> None:
        try:
            self.fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as err:
            access = " (on Linux: sudo usermod -aG input $USER, then log in again)" if err.errno == errno.EACCES else ""
            raise ValueError(f"cannot open gamepad {path!r}: {err.strerror}{access}") from None
        shape = joystick_shape(self.fd)
        if shape is None:
            # an evdev device (/dev/input/eventN) has 24-byte events: read as 8-byte ones they would be
            # random buttons and axes, and a file or /dev/null would be an e-stop that never fires
            os.close(self.fd)
            raise ValueError(f"{path!r} is not a joystick device (/dev/input/jsN)")
        self.num_axes, self.num_buttons = shape
        self.presses: set = set()  # buttons pressed since was_pressed() last asked: a tap between two polls counts
        self._partial = b""  # the start of an event a read split, completed by the next read
        self.path = path
        self.axes: dict = {}
        self.buttons: dict = {}

    def require(self, buttons: Dict[str, int], axes: Dict[str, int]) -> None:
        """ValueError naming each button or axis (by its option) that this device does not have:
        an e-stop on a button that does not exist would never fire."""
        missing = [f"{name} {i}" for name, i in buttons.items() if not 0 <= i < self.num_buttons]
        missing += [f"{name} {i}" for name, i in axes.items() if not 0 <= i < self.num_axes]
        if missing:
            buttons_span, axes_span = (f"0-{n - 1}" if n else "none" for n in (self.num_buttons, self.num_axes))
            raise ValueError(f"gamepad {self.path!r} has buttons {buttons_span} and axes {axes_span}: no {', '.join(missing)}")

    def poll(self) -> None:
        """Read every pending event; GamepadLost if the device is gone (the kernel answers ENODEV)."""
        while True:
            try:
                data = os.read(self.fd, self.EVENT.size * 64)
            except BlockingIOError:
                return
            except OSError as err:
                raise GamepadLost(f"gamepad {self.path!r} lost ({err.strerror})") from None
            if not data:
                return
            data = self._partial + data
            whole = len(data) - len(data) % self.EVENT.size
            self._partial = data[whole:]
            for offset in range(0, whole, self.EVENT.size):
                _, value, kind, number = self.EVENT.unpack_from(data, offset)
                kind &= 0x7F
                if kind == 1:
                    self.buttons[number] = bool(value)
                    if value:
                        self.presses.add(number)
                elif kind == 2:
                    self.axes[number] = max(-1.0, value / 32767.0)  # the kernel reports -32768..32767

    def was_pressed(self, button: int) -> bool:
        """Whether `button` is down, or went down since the last call (released again before a poll saw it)."""
        pressed = button in self.presses or self.buttons.get(button, False)
        self.presses.discard(button)
        return pressed

    def close(self) -> None:
        try:
            os.close(self.fd)
        except OSError:  # already gone with the device
            pass
