"""``dark:LEVEL``: an example DRVS algorithm plugin — the regions darker than a grey level.

Each connected region of pixels whose grey level is below LEVEL (an integer 0-255)
and that covers at least ``min_area`` pixels is one object, labelled ``dark``. The
vision system then puts each outline on the floor (lifting it with the depth image
when there is one), clips it to the request's region of interest and calls the
robot back.

Copy this file and ``pyproject.toml`` to write your own algorithm: it needs a
``name``, a ``syntax``, a ``parse`` that checks the parameters and a ``detect`` that
finds the objects in a frame (see :mod:`drvs.algorithms.base`).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from drvs.algorithms import Algorithm, AlgorithmError, PixelObject, outlines_of_mask


class Dark(Algorithm):
    """``dark:LEVEL``: connected regions whose grey level is below LEVEL."""

    name = 'dark'  # what requests call it: dark:LEVEL
    syntax = 'dark:LEVEL'  # shown in error messages and documentation
    label = 'dark'  # what each object is, sent to the robot with its outline

    def __init__(self, min_area: float = 20.0, epsilon: float = 1.0):
        # DRVS instantiates the entry point's class with no arguments: give every argument a default.
        self.min_area = min_area  # smallest object, pixels
        self.epsilon = epsilon  # outline simplification, pixels

    def parse(self, params: str) -> int:
        """LEVEL from the text after ``dark:``; the server and the vision systems call this.

        The message of the error is what the robot gets back (status INVALID): name
        the algorithm, the field and the problem.
        """
        text = params.strip()
        if not text:
            raise AlgorithmError('algorithm: dark needs LEVEL, an integer 0-255, e.g. dark:100')
        try:
            level = int(text, 10)
        except ValueError:
            raise AlgorithmError(f'algorithm: dark LEVEL must be an integer 0-255, got {text!r}') from None
        if not 0 <= level <= 255:
            raise AlgorithmError(f'algorithm: dark LEVEL must be in 0-255, got {level}')
        return level

    def detect(self, frame, params: int) -> list[PixelObject]:
        """The dark regions of ``frame.rgb`` ((H, W, 3) uint8), outlined in pixels.

        ``params`` is what :meth:`parse` returned. A vision system may run detect on
        two worker threads at once: it must not change shared state (this one keeps none).
        """
        grey = cv2.cvtColor(np.ascontiguousarray(frame.rgb[..., :3]), cv2.COLOR_RGB2GRAY)
        mask = (grey < params).astype(np.uint8)
        # outlines_of_mask traces each connected region along its pixels' edges (DRVS pixel
        # coordinates: pixel (row v, column u) covers [u, u+1] x [v, v+1]).
        return [
            dataclasses.replace(found, label=self.label)
            for found in outlines_of_mask(mask, self.min_area, self.epsilon)
        ]
