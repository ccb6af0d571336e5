"""The README's commands keep working: every fenced shell command of README.md is run here, or checked
in the strongest form that can run here, or listed with the reason it cannot. A command added to the
README without an entry below fails `test_every_command_is_accounted_for`, and so does an entry whose
command left the README. Also: the README stays a short guide (<= 250 lines), its links and anchors
resolve, its results table is the one docs/results.md holds, and its printout is the main job's report.

How each kind of command is checked:
- RUN: run as written, in README order, in a scratch folder whose ../shared/data is the real data
  (the README's commands name that folder; skipped when it is absent).
- MAKE: `make -n` with the same variables (the dry run: the target exists, its recipe expands, and
  every script it calls is in the repo), because the real run takes minutes to an hour.
- HELP: the command's own `--help` (subcommand included), which must list every `--flag` the README
  gives it, because its input (a running node, a map, a server) is not here.
- ROS2: no `ros2` CLI here (ROS 2 comes from PyPI wheels), so what the command names is checked in
  the package: launch arguments, executables, parameters (and whether they change at run time),
  services, installed share/ files.
- NOT_RUN: the reason.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, SHARED_DATA

README = REPO / 'README.md'
MAX_LINES = 250
BIN = Path(sys.executable).parent  # the venv running the tests holds the lln-* console scripts

RUN = {
    'lln-bag from-images ../shared/data/rtabmap_loop rtabmap_bag --topic /camera/image_raw --fps 4',
    'lln-bag info rtabmap_bag',
}
MAKE = {
    'make main',
    'make test',
    'make main ARGS=--download',
    'make main ARGS="--dataset aligned:MAP_DIR,QUERY_DIR,2"',
    'OUT=out/gardens make main ARGS=--download',
}
HELP = {
    'lln-bag play rtabmap_bag --clock --wait-subscribers 1': 'plays only once the nodes subscribe',
    'lln-map info /tmp/run.db': 'the map is the one the launch line above writes',
    "lln-map export /tmp/run.db 'milvus://milvus.example:19530/lln?map=city'": 'needs a Milvus server',
    'lln-map merge robot1.db robot2.db fleet.db': "needs two robots' maps (test/test_map_merge.py merges real ones)",
    'python scripts/loop_closure_client.py --min-score 46.1 --min-gap 5 --require-pose --out closures.jsonl '
    '--ros-args -p use_sim_time:=true': 'needs a running matcher',
}
ROS2 = {
    'export FASTRTPS_DEFAULT_PROFILES_FILE=$(ros2 pkg prefix lln_ros)/share/lln_ros/config/fastdds_large_data.xml',
    'ros2 launch lln_ros lln.launch.py image:=/image_raw mode:=mapping map_path:=$HOME/maps/office.db '
    'visualize:=true rviz:=true',
    'ros2 launch lln_ros lln.launch.py mode:=mapping use_sim_time:=true reliability:=reliable frame_queue:=100 '
    'map_path:=/tmp/run.db',
    'ros2 param set /lln_matcher min_score 46.1',
    'ros2 service call /lln_matcher/info std_srvs/srv/Trigger',
}
NOT_RUN = {
    'ros2 run usb_cam usb_cam_node_exe': 'a camera driver of another package, and a camera',
    'colcon build --packages-select lln_ros && source install/setup.bash': (
        'a colcon build takes minutes; test/test_package.py builds the package with colcon and checks the '
        'ament index entry and the executables'
    ),
}
NODES = {'lln_extractor': 'extractor', 'lln_matcher': 'matcher', 'lln_visualizer': 'visualizer'}


def readme_commands(text: str) -> list[str]:
    """Every command of the ```bash / ```sh / ```shell blocks, in order: `\\` continuations joined,
    comment lines dropped, a trailing `  # comment` cut, whitespace runs made single."""
    commands, block, pending = [], None, ''
    for line in text.splitlines():
        fence = re.match(r'^\s*```\s*(\S*)', line)
        if fence:
            block = None if block is not None else fence.group(1)
            continue
        if block not in ('bash', 'sh', 'shell'):
            continue
        line = pending + line.strip()
        if line.endswith('\\'):
            pending = line[:-1] + ' '
            continue
        pending = ''
        line = re.sub(r'\s+#\s.*$', '', line).strip()
        if line and not line.startswith('#'):
            commands.append(' '.join(line.split()))
    return commands


def commands() -> list[str]:
    return readme_commands(README.read_text())


def env() -> dict:
    return {**os.environ, 'PATH': f'{BIN}{os.pathsep}{os.environ.get("PATH", "")}', 'PYTHONPATH': str(REPO)}


def test_readme_commands_are_extracted():
    """The extractor of commands itself: continuations, comments, other fences."""
    text = '```bash\n# a comment\nmake a   # why\nlln-x --a 1 \\\n    --b 2\n```\n```text\nnot a command\n```\n'
    assert readme_commands(text) == ['make a', 'lln-x --a 1 --b 2']


def test_every_command_is_accounted_for():
    listed = RUN | MAKE | set(HELP) | ROS2 | set(NOT_RUN)
    found = commands()
    unlisted = [c for c in found if c not in listed]
    assert not unlisted, f'README commands neither run nor listed in test/test_readme.py: {unlisted}'
    stale = sorted(listed - set(found))
    assert not stale, f'test/test_readme.py lists commands the README no longer has: {stale}'


def test_runnable_commands_run(tmp_path):
    if not SHARED_DATA.exists():
        pytest.skip(f'real data not available: {SHARED_DATA} is absent (the README commands name it)')
    (tmp_path / 'shared').mkdir()
    (tmp_path / 'shared' / 'data').symlink_to(SHARED_DATA.resolve())
    work = tmp_path / 'work'
    work.mkdir()
    ran = 0
    for command in commands():
        if command not in RUN:
            continue
        r = subprocess.run(command, shell=True, cwd=work, env=env(), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, f'{command}\n{r.stdout}\n{r.stderr}'
        ran += 1
    assert ran == len(RUN)
    assert 'messages:  84' in r.stdout  # lln-bag info of the bag the line before wrote


@pytest.mark.parametrize('command', sorted(MAKE))
def test_make_commands_dry_run(command):
    words = shlex.split(command)
    at = words.index('make')
    variables = dict(w.split('=', 1) for w in words[:at])
    r = subprocess.run(
        ['make', '-n', *words[at + 1 :]], cwd=REPO, env={**env(), **variables}, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    scripts = re.findall(r'^bash (\S+)', r.stdout, re.M)
    assert scripts, r.stdout  # every README make target runs the setup script at least
    for script in scripts:
        assert (REPO / script).is_file(), f'{command}: make -n runs {script}, which is not in the repo'
    for word in words[at + 1 :]:
        if word.startswith('ARGS='):
            assert word[5:] in r.stdout, f'{command}: ARGS do not reach the script'


@pytest.mark.parametrize('command', sorted(HELP))
def test_help_lists_every_flag(command):
    words = shlex.split(command)
    if '--ros-args' in words:
        words = words[: words.index('--ros-args')]  # rclpy's arguments, not the program's
    if words[0] == 'python':
        program, rest = [sys.executable, str(REPO / words[1])], words[2:]
    else:
        program, rest = [str(BIN / words[0])], words[1:]
        if rest and not rest[0].startswith('-'):
            program.append(rest.pop(0))  # a subcommand (lln-bag play, lln-map info)
    r = subprocess.run([*program, '--help'], cwd=REPO, env=env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for flag in (w.split('=', 1)[0] for w in rest if w.startswith('--')):
        assert re.search(rf'{re.escape(flag)}\b', r.stdout), f'{command}: {flag} is not in its --help'


def launch_arguments() -> set[str]:
    return set(re.findall(r"DeclareLaunchArgument\(\s*'(\w+)'", (REPO / 'launch' / 'lln.launch.py').read_text()))


def node_parameters(node: str):
    from importlib import import_module

    return import_module(f'lln_ros.nodes.{NODES[node]}').PARAMETERS


@pytest.mark.parametrize('command', sorted(ROS2))
def test_ros2_commands_name_what_the_package_has(command):
    words = shlex.split(command.split('&&')[0])
    for path in re.findall(r'share/lln_ros/(\S+)', command):
        assert (REPO / path).is_file(), f'{command}: {path} is not in the repo'
        assert path.split('/')[0] in (REPO / 'setup.py').read_text(), f'setup.py does not install {path}'
    if words[0] == 'export':
        return
    assert words[0] == 'ros2'
    if words[1] == 'launch':
        assert words[2:4] == ['lln_ros', 'lln.launch.py']
        declared = launch_arguments()
        for name in (w.split(':=')[0] for w in words[4:]):
            assert name in declared, f'{command}: launch argument {name} is not declared in launch/lln.launch.py'
    elif words[1] == 'param':
        assert words[2] == 'set'
        param = node_parameters(words[3].lstrip('/'))[words[4]]
        assert param.dynamic, f'{command}: {words[4]} is read-only'
    elif words[1] == 'service':
        node, service = words[3].lstrip('/').split('/')
        source = (REPO / 'lln_ros' / 'nodes' / f'{NODES[node]}.py').read_text()
        assert f"'~/{service}'" in source, f'{command}: {node} has no service ~/{service}'
    else:
        raise AssertionError(f'{command}: no check for ros2 {words[1]}')


def test_readme_is_a_short_guide():
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_LINES, f'README.md has {len(lines)} lines, at most {MAX_LINES}'


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    return re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')


def anchors(path: Path) -> set[str]:
    text = re.sub(r'```.*?```', '', path.read_text(), flags=re.S)  # a `# comment` in a block is no heading
    return {slug(h) for h in re.findall(r'^#+ (.+)$', text, re.M)}


@pytest.mark.parametrize('page', ['README.md', *sorted(p.relative_to(REPO).as_posix() for p in REPO.glob('docs/*.md'))])
def test_links_resolve(page):
    """Every relative link and image of the README and the docs pages names a file that exists, and
    every #anchor a heading of that file."""
    source = REPO / page
    text = re.sub(r'```.*?```', '', source.read_text(), flags=re.S)
    broken = []
    for target in re.findall(r'\]\(([^)\s]+)\)', text):
        if re.match(r'[a-z]+:', target):
            continue  # http(s), mailto
        path, _, anchor = target.partition('#')
        file = (source.parent / path).resolve() if path else source
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == '.md' and anchor not in anchors(file):
            broken.append(target)
    assert not broken, f'{page}: links to nothing: {broken}'


def table_rows(text: str) -> list[list[str]]:
    return [
        [c.strip().replace('**', '') for c in line.strip().strip('|').split('|')]
        for line in text.splitlines()
        if line.startswith('|') and not line.startswith('|---')
    ]


def section(text: str, heading: str) -> str:
    start = text.index(heading)
    end = text.find('\n## ', start + len(heading))
    return text[start : end if end > 0 else None]


def test_results_table_is_the_one_results_md_holds():
    """The README's one results table: every figure as docs/results.md (make results) has it, in the
    shipped-defaults section, per dataset and lln-eval row."""
    readme = README.read_text()
    table = next(t for t in readme.split('\n\n') if '(`lln-eval` row)' in t)
    rows = table_rows(table)
    header, body = rows[0], rows[1:]
    results = section((REPO / 'docs' / 'results.md').read_text(), '## lln-eval output: the shipped defaults (landmark')
    datasets = {'Nordland test split': '### summer-vs-winter[0.7:1]', 'rtabmap_loop': '### rtabmap_loop'}
    checked = 0
    for row in body:
        method = re.search(r'`([^`]+)`', row[0]).group(1)
        for column, value in zip(header[1:], row[1:], strict=True):
            name, metric = (s.strip() for s in column.split(','))
            sub = section(results, datasets[name])
            sub = sub[: sub.find('\n### ', 5) if sub.find('\n### ', 5) > 0 else None]
            measured = table_rows(sub)
            cols = measured[0]
            got = next(r for r in measured[1:] if r[0] == method)[cols.index(metric)]
            assert got == value, f'{method} {column}: README {value}, results.md {got}'
            checked += 1
    assert checked == len(body) * (len(header) - 1) >= 12


def test_printout_is_the_main_jobs_report():
    """The metric lines of the README's printout are the online/offline table of the report the main
    job wrote (docs/main_job/results_online.md)."""
    readme = README.read_text()
    printout = re.search(r'```text\n(summer-vs-winter.*?)```', readme, re.S).group(1)
    report = {r[0]: r[1:3] for r in table_rows((REPO / 'docs' / 'main_job' / 'results_online.md').read_text())}
    lines = [line.split() for line in printout.splitlines() if re.match(r'^(P@|R@|AUC)', line)]
    assert len(lines) == 6
    for metric, online, offline, _ in lines:
        assert report[metric] == [online, offline], metric
    same = re.search(r'same top-1\s+(\S+)', printout).group(1)
    assert report['same top-1'][0] == same
