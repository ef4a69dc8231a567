"""The hand-run tutorial (docs/tutorials/by-hand.md, "Talking to a running DRVS by hand"), run as written.

The test reads the page's shell blocks and runs them in order
against a private master: terminal 1's ``roscore`` is the harness's master (its
``ROS_MASTER_URI`` is in the environment, which ``scripts/env.sh`` keeps),
terminal 2's ``run_scenario.sh ... --stay`` runs in the background (with ``--out`` in
the test's folder), and each
command of terminal 3 and of the blocks after it runs once the robot is done.
The ``# ...`` lines under a command are its documented output: every one must
appear in what it prints, with numbers, times and ``...`` free to differ.
README.md's short example is made of this page's commands and output, so it is
run here too.
"""

from pathlib import Path

import pytest

from drvs.testing import RosHarness, wait_for
from drvs.testing.doc_examples import commands, output_pattern, shell_blocks

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / 'docs' / 'tutorials' / 'by-hand.md'


def test_the_tutorials_commands_parse_into_the_three_terminals():
    blocks = shell_blocks(PAGE)
    assert len(blocks) >= 3, blocks
    assert [command for command, _ in commands(blocks[0])] == ['source scripts/env.sh', 'roscore']
    ((runner, _),) = commands(blocks[1])
    assert runner.startswith('scripts/run_scenario.sh') and '--stay' in runner
    asked = commands(blocks[2])
    assert asked[-1][0].startswith('rosservice call /drvs/detect_object_boundary')
    assert 'accepted: True' in asked[-1][1]
    assert output_pattern('x 5.694..6.095, (1.5, ...)').fullmatch('x 5.7..6.1, (1.25, 2, 3)')


# A whole run of the localisation world and the commands after it, about half a minute: slow-marked
# (make test-slow); the default suite runs the same world with --record in test/scenarios.
@pytest.mark.slow
def test_the_hand_run_example_works_as_written(ros: RosHarness):
    terminal1, terminal2, terminal3, *more = (commands(block) for block in shell_blocks(PAGE))
    assert [command for command, _ in terminal1] == [
        'source scripts/env.sh',
        'roscore',
    ]  # the harness's master
    ((run_command, _),) = terminal2
    # As written, plus --out: its default (out/localisation in the checkout) is a fixed path that
    # a second run in the same checkout would find in use.
    out = ros.root / 'out'
    command = f'source scripts/env.sh && exec {run_command} --out {out}'
    runner = ros.spawn('run_scenario', ['bash', '-c', command])
    wait_for(
        lambda: 'keep running' in runner.log() or not runner.running(),
        150,
        'the scenario to finish and stay up',
        interval=0.5,
        on_timeout=runner.describe,
    )
    assert runner.running(), f'run_scenario.sh --stay exited\n{runner.describe()}'
    assert 'robot reached' in runner.log(), runner.describe()

    assert terminal3[0][0] == 'source scripts/env.sh'  # ros.run sources it for every command
    for command, documented in terminal3[1:] + [line for block in more for line in block]:
        result = ros.run(command, timeout=60)
        assert result.returncode == 0, f'{command}\n{result.stdout}\n{result.stderr}'
        printed = result.stdout.splitlines()
        for line in documented:
            pattern = output_pattern(line.strip())
            assert any(
                pattern.fullmatch(out.strip()) for out in printed
            ), f'{command!r} did not print {line!r}:\n{result.stdout}\n{result.stderr}'


def test_the_readme_example_is_made_of_the_tutorials_commands_and_output():
    """README.md's ten-line example: each command, and each line of output it shows, is on the page."""
    (readme,) = [block for block in shell_blocks(REPO / 'README.md') if 'drvs_ask' in block]
    tutorial = {}
    for block in shell_blocks(PAGE):
        for command, documented in commands(block):
            tutorial.setdefault(command, []).extend(documented)
    shown = commands(readme)
    assert len(shown) >= 3, readme
    for command, documented in shown:
        assert command in tutorial, f'README.md runs {command!r}, which {PAGE.name} does not'
        assert set(documented) <= set(tutorial[command]), (command, documented, tutorial[command])
