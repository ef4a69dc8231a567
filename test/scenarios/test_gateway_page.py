"""The floor-plan page in a real browser: ``run_scenario.sh --gateway`` on the localisation world, and
headless Chromium on its page. Every camera's field of view is drawn, the robot's marker moves, a
wrong token shows an error (not a blank page).

Skipped, with the reason, only where Chromium cannot run (scripts/setup.sh installs it); never in CI
(``CI`` set: a missing browser fails). With ``DRVS_PAGE_SCREENSHOT=path.png`` the page is also
written there (that is how docs/gateway-page.png is made).
"""

import json
import os
import urllib.error
import urllib.request

import pytest

from drvs.testing import RosHarness, free_port, wait_for
from drvs.testing.browser import headless_chromium, unavailable
from drvs.testing.scenario import start_scenario

WORLD = 'worlds/localisation.yaml'


@pytest.fixture
def browser_ready():
    reason = unavailable()
    if reason and os.environ.get('CI'):
        pytest.fail(f'the browser test must run in CI: {reason}')
    if reason:
        pytest.skip(reason)


def test_the_floor_plan_shows_cameras_and_a_moving_robot_and_refuses_a_wrong_token(
    ros: RosHarness, browser_ready
):
    from selenium.webdriver.common.by import By

    url = f'http://127.0.0.1:{free_port()}'
    run = start_scenario(
        ros, WORLD, '--stay', '--gateway', '--gateway-bind', url.removeprefix('http://'), timeout=120
    )
    token_file = run.out / 'gateway.token'

    def gateway_up():
        assert run.runner.running(), run.logs()
        if not token_file.exists() or not token_file.read_text().strip():
            return None
        try:
            with urllib.request.urlopen(f'{url}/v1/openapi.json', timeout=2):
                return token_file.read_text().strip()
        except OSError:
            return None

    token = wait_for(gateway_up, 60, 'the run to start drvs_gateway', interval=0.2, on_timeout=run.logs)

    def registry_heard():  # 503 until the gateway has heard /drvs/registry
        request = urllib.request.Request(
            f'{url}/v1/vision_systems', headers={'Authorization': f'Bearer {token}'}
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as response:
                return {entry['name'] for entry in json.load(response)['vision_systems']}
        except urllib.error.HTTPError as error:
            assert error.code == 503, error
            return None

    registry = wait_for(registry_heard, 20, 'the registry through the gateway', interval=0.2)
    assert len(registry) == 2, registry

    with headless_chromium(1000, 900) as driver:
        driver.get(url + '/')
        form = wait_for(lambda: driver.find_element(By.ID, 'login').is_displayed(), 15, 'the token form')
        assert form
        driver.find_element(By.ID, 'token').send_keys('drvs.0000.wrong')
        driver.find_element(By.CSS_SELECTOR, '#login button').click()
        error = wait_for(
            lambda: (box := driver.find_element(By.ID, 'error')).is_displayed()
            and '401' in box.text
            and box.text,
            15,
            'the error for a wrong token',
        )
        assert '401' in error and 'token' in error.lower(), error
        assert driver.find_element(By.ID, 'login').is_displayed()  # asked again, not a blank page

        driver.find_element(By.ID, 'token').send_keys(token)
        driver.find_element(By.CSS_SELECTOR, '#login button').click()

        def attributes(selector, name):  # read in one go: the page redraws its elements
            return driver.execute_script(
                'return [...document.querySelectorAll(arguments[0])].map(e => e.getAttribute(arguments[1]))',
                selector,
                name,
            )

        def fields_of_view():
            return set(attributes('#fovs polygon.fov', 'data-name')) == registry

        wait_for(fields_of_view, 20, 'every field of view drawn', interval=0.2, on_timeout=run.logs)
        assert not driver.find_element(By.ID, 'error').is_displayed()
        assert not driver.find_element(By.ID, 'login').is_displayed()
        labels = driver.execute_script(
            "return [...document.querySelectorAll('#labels .fov-label')].map((e) => e.textContent)"
        )
        assert sorted(labels) == ['vs1', 'vs2']

        def robot_at():
            markers = attributes('#robots g.robot', 'transform')
            return markers[0] if markers else None

        first = wait_for(robot_at, 40, "the robot's marker", interval=0.2, on_timeout=run.logs)
        moved = wait_for(
            lambda: (now := robot_at()) != first and now, 40, "the robot's marker to move", interval=0.2,
            on_timeout=run.logs,
        )  # fmt: skip
        assert moved != first
        wait_for(lambda: attributes('#paths polyline.path', 'points'), 20, "the robot's path")
        shot = driver.get_screenshot_as_png()
        (ros.root / 'gateway-page.png').write_bytes(shot)
        if os.environ.get('DRVS_PAGE_SCREENSHOT'):
            with open(os.environ['DRVS_PAGE_SCREENSHOT'], 'wb') as out:
                out.write(shot)
