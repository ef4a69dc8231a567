"""RViz on a running scenario: ``run_scenario.sh --rviz`` under a virtual display, one screenshot.

Slow (a whole scenario plus RViz on a software renderer). Skipped with the reason
where RViz is not installed (``make rviz-setup`` installs it) or no virtual
display can be started. With ``DRVS_RVIZ_SCREENSHOT=path.png`` the screenshot is
also written there (that is how docs/rviz.png is made).
"""

import os
import shutil

import cv2
import numpy as np
import pytest

from drvs.ros.markers import FIELD_OF_VIEW_COLOUR
from drvs.testing import RosHarness, wait_for
from drvs.testing.screen import DisplayUnavailable, VirtualDisplay

pytestmark = pytest.mark.slow

WIDTH, HEIGHT = 1200, 900  # rviz/drvs.rviz's window
FIELD_OF_VIEW_RGB = tuple(round(255 * channel) for channel in FIELD_OF_VIEW_COLOUR[:3])
PLAN_RGB = (255, 140, 0)  # the robot's plan in rviz/drvs.rviz


def pixels_of(image: np.ndarray, rgb: tuple[int, int, int]) -> int:
    """Pixels drawn in colour ``rgb`` (within shading)."""
    return int((np.abs(image.astype(int) - np.array(rgb)).max(axis=-1) <= 40).sum())


@pytest.fixture
def display():
    if shutil.which('rviz') is None:
        pytest.skip("Debian's rviz is not installed: run make rviz-setup")
    try:
        with VirtualDisplay(WIDTH, HEIGHT) as display:
            yield display
    except DisplayUnavailable as error:
        pytest.skip(f'no virtual display: {error}')


def test_rviz_shows_the_running_scenario(ros: RosHarness, display: VirtualDisplay):
    runner = ros.spawn(
        'run_scenario',
        ['bash', 'scripts/run_scenario.sh', 'worlds/localisation.yaml', '--external-master', '--stay',
         '--rviz', '--out', str(ros.root / 'out')],
        env={'DISPLAY': display.name, 'LIBGL_ALWAYS_SOFTWARE': '1'},
    )  # fmt: skip

    def drawn():
        if not runner.running():
            raise AssertionError(f'run_scenario.sh exited\n{runner.describe()}')
        shot = display.screenshot()
        return (
            [shot] if pixels_of(shot, FIELD_OF_VIEW_RGB) > 500 and pixels_of(shot, PLAN_RGB) > 100 else None
        )

    # RViz draws both cameras' fields of view (latched markers) and, once the
    # robot has found itself and its station through DRVS, its plan.
    (image,) = wait_for(
        drawn,
        180,
        'RViz to draw the fields of view and the plan',
        interval=0.5,
        on_timeout=lambda: runner.describe()
        + (ros.root / 'out' / 'rviz.log').read_text(errors='replace')[-3000:],
    )
    assert image.shape == (HEIGHT, WIDTH, 3)
    assert image.std() > 10, 'the screen is one flat colour'
    assert len(np.unique(image.reshape(-1, 3)[::7], axis=0)) > 20, 'too few colours for a drawn scene'
    target = os.environ.get('DRVS_RVIZ_SCREENSHOT')
    if target:
        cv2.imwrite(target, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
