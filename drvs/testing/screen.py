"""A virtual X display (Xvfb) whose screen can be read as an image, for GUI tests.

``Xvfb -fbdir DIR`` keeps its framebuffer in ``DIR/Xvfb_screen0``, an XWD file
(the X Window Dump format) that the server updates in place, so a screenshot
is a read of that file: no ``xwd`` or ImageMagick needed. ``-displayfd`` lets
Xvfb choose a free display number itself, so parallel tests never collide.

>>> with VirtualDisplay(640, 480) as display:            # doctest: +SKIP
...     run_gui_program(env={'DISPLAY': display.name})
...     image = display.screenshot()                      # (480, 640, 3) uint8, RGB
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ['DisplayUnavailable', 'VirtualDisplay', 'read_xwd']

_HEADER = struct.Struct('>25I')  # XWDFileHeader: 25 big-endian CARD32
_COLOUR_ENTRY = 12  # XWDColor: pixel CARD32, red/green/blue CARD16, flags and pad bytes
_ZPIXMAP = 2


class DisplayUnavailable(RuntimeError):
    """No virtual display can be started here (Xvfb missing or failing); the message says why."""


def read_xwd(data: bytes) -> np.ndarray:
    """An (height, width, 3) uint8 RGB image from an XWD dump of a 24- or 32-bit TrueColor screen.

    :raises ValueError: for another format, naming what it is.
    """
    if len(data) < _HEADER.size:
        raise ValueError(f'XWD: {len(data)} bytes is shorter than the header')
    (header_size, version, pixmap_format, _depth, width, height, _xoffset, byte_order, _unit, _bit_order,
     _pad, bits_per_pixel, bytes_per_line, _visual, red_mask, green_mask, blue_mask, _bits_per_rgb,
     _entries, colours, *_window) = _HEADER.unpack_from(data)  # fmt: skip
    if version != 7 or pixmap_format != _ZPIXMAP or bits_per_pixel not in (24, 32):
        raise ValueError(
            f'XWD: version {version}, format {pixmap_format}, {bits_per_pixel} bits per pixel; '
            'expected version 7, ZPixmap (2), 24 or 32 bits per pixel'
        )
    start = header_size + colours * _COLOUR_ENTRY
    size = height * bytes_per_line
    if len(data) < start + size:
        raise ValueError(f'XWD: {len(data)} bytes, the {width}x{height} image needs {start + size}')
    rows = np.frombuffer(data, np.uint8, size, start).reshape(height, bytes_per_line)
    step = bits_per_pixel // 8
    pixels = rows[:, : width * step].reshape(height, width, step).astype(np.uint32)
    order = range(step) if byte_order == 0 else reversed(range(step))  # 0: least significant byte first
    value = sum(pixels[:, :, index] << (8 * shift) for shift, index in enumerate(order))
    channels = []
    for mask in (red_mask, green_mask, blue_mask):
        shift = (mask & -mask).bit_length() - 1
        channels.append(((value & mask) >> shift).astype(np.uint8))
    return np.stack(channels, axis=-1)


class VirtualDisplay:
    """An Xvfb server on a display number of its own choosing; stopped by :meth:`close`.

    :param width, height: the screen size in pixels (24-bit colour).
    :param timeout: seconds to wait for the server to come up.
    :raises DisplayUnavailable: if Xvfb is not installed or does not start.
    """

    def __init__(self, width: int = 1280, height: int = 960, timeout: float = 20.0):
        executable = shutil.which('Xvfb')
        if executable is None:
            raise DisplayUnavailable(
                'Xvfb is not installed (Debian package xvfb; make rviz-setup installs it)'
            )
        self._folder = Path(tempfile.mkdtemp(prefix='drvs-xvfb-'))
        read_end, write_end = os.pipe()
        self._process = subprocess.Popen(
            [executable, '-displayfd', str(write_end), '-screen', '0', f'{width}x{height}x24',
             '-fbdir', str(self._folder), '-nolisten', 'tcp', '-noreset'],
            pass_fds=(write_end,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        )  # fmt: skip
        os.close(write_end)
        try:
            number = self._read_display_number(read_end, timeout)
        except DisplayUnavailable:
            self.close()
            raise
        finally:
            os.close(read_end)
        self.name = f':{number}'

    def _read_display_number(self, read_end: int, timeout: float) -> int:
        deadline = time.monotonic() + timeout
        text = b''
        os.set_blocking(read_end, False)
        while not text.endswith(b'\n'):
            if self._process.poll() is not None:
                error = self._process.stderr.read().decode(errors='replace').strip().splitlines()
                raise DisplayUnavailable(
                    f'Xvfb exited with {self._process.returncode}: {" ".join(error[-3:])}'
                )
            if time.monotonic() > deadline:
                raise DisplayUnavailable(f'Xvfb did not report a display within {timeout:g} s')
            try:
                text += os.read(read_end, 64)
            except BlockingIOError:
                time.sleep(0.05)
        return int(text)

    def screenshot(self) -> np.ndarray:
        """The screen now, (height, width, 3) uint8 RGB."""
        return read_xwd((self._folder / 'Xvfb_screen0').read_bytes())

    def close(self) -> None:
        """Stop the server and remove its framebuffer folder."""
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process.stderr.close()
        shutil.rmtree(self._folder, ignore_errors=True)

    def __enter__(self) -> VirtualDisplay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
