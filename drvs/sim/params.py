"""The parameters (``~params``) of the simulation's nodes and of the scenario recorder, each node's
read once into its dataclass; docs/nodes/world_sim.md, sim_camera.md and scenario_recorder.md's
tables are generated from them (:mod:`drvs.ros.param_docs`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from drvs.common.settings import POSITIVE, REQUIRED, Range, Settings, at_least, between, one_of, param

__all__ = [
    'COMPRESSIONS',
    'FACTOR',
    'RecorderSettings',
    'SimCameraParams',
    'SiteLinkSettings',
    'WorldSimSettings',
]

COMPRESSIONS = ('jpeg', 'png')
MASTER_URI = Range(
    lambda value: re.fullmatch(r'http://[^/:\s]+:[0-9]{1,5}/?', value) is not None,
    'must be a ROS master URI http://HOST:PORT/',
    'http://HOST:PORT/',
)
GLOBAL_NAMES = Range(
    lambda value: bool(value.strip())
    and all(re.fullmatch(r'(/[A-Za-z]\w*)+', name.strip()) for name in value.split(',')),
    'must be one or more global topic names (/name/name), comma-separated or a list',
    'global names',
)
FACTOR = Range(lambda value: 0 < value <= 1, 'must be above 0 and at most 1', '0 < x ≤ 1')


@dataclass(frozen=True)
class WorldSimSettings(Settings):
    world: str = param(REQUIRED, 'the world file')
    rate: float = param(30.0, 'simulation steps and publications per second', unit='Hz', check=POSITIVE)
    cmd_timeout: float = param(
        0.5, 'a robot stops after this long without a message on its `cmd_vel`', unit='s', check=POSITIVE
    )
    real_time_factor: float | None = param(
        None,
        'simulated seconds per wall second; below 1 needs `/use_sim_time` true (world_sim then publishes '
        '`/clock`)',
        check=FACTOR,
        default_text="the world's `real_time_factor` (1)",
    )


@dataclass(frozen=True)
class SimCameraParams(Settings):
    world: str = param(REQUIRED, 'the world file')
    cameras: str = param(
        '',
        'the cameras to publish, comma-separated (`vs1,vs2`) or a YAML list (`[vs1, vs2]`)',
        default_text='every vision system of the world',
        separator=',',
    )
    rate: float = param(10.0, 'frames per second per subscribed camera', unit='Hz', check=POSITIVE)
    depth: bool = param(True, 'publish depth images')
    compression: str = param('jpeg', 'the format of `image_raw/compressed`', check=one_of(*COMPRESSIONS))
    jpeg_quality: int = param(90, 'JPEG quality of `image_raw/compressed`', check=between(1, 100))
    poses_topic: str = param('/world_sim/poses', "world_sim's pose topic")

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The names in ``~cameras``, in order; empty for every camera."""
        return tuple(name.strip() for name in self.cameras.split(',') if name.strip())


@dataclass(frozen=True)
class RecorderSettings(Settings):
    world: str = param(REQUIRED, 'the world file of the run')
    out: str = param(REQUIRED, 'the folder for `summary.json`, `trace.json`, `run.png` and `status.line`')
    cpu_period: float = param(1.0, 'time between CPU samples of every node', unit='s', check=POSITIVE)


@dataclass(frozen=True)
class SiteLinkSettings(Settings):
    master: str = param(REQUIRED, "the other site's ROS master, whose topics it copies", check=MASTER_URI)
    topics: str = param(
        REQUIRED,
        'the topics to copy, comma-separated (`/clock,/world_sim/poses`) or a YAML list',
        check=GLOBAL_NAMES,
        separator=',',
    )
    poll_period: float = param(
        0.5,
        "time between two questions to the other master for the topics' publishers",
        unit='s',
        check=POSITIVE,
    )
    timeout: float = param(
        2.0,
        'deadline of each call to the other master or a publisher, and of each handshake',
        unit='s',
        check=POSITIVE,
    )
    queue_size: int = param(10, 'messages of a topic waiting to be published here', check=at_least(1))

    @property
    def topic_names(self) -> tuple[str, ...]:
        """The names in ``~topics``, in order, each once."""
        return tuple(dict.fromkeys(name.strip() for name in self.topics.split(',') if name.strip()))
