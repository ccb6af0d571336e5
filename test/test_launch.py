"""launch/lln.launch.py and the files it points at, as colcon installs them. `launch` / `launch_ros`
are not installable here, so the file is checked statically (as test_nodes.py does): every argument
issue 16 asks for is declared with a sane default, every node gets the namespace, log level and
sim-time switches, and every installed file or executable it names exists."""

from __future__ import annotations

import ast

import yaml

REQUIRED = {
    'image',
    'image_transport',
    'reliability',
    'frame_queue',
    'mode',
    'feed',
    'map_path',
    'verify',
    'use_sim_time',
    'namespace',
    'log_level',
    'visualize',
    'rviz',
    'dds_profile',
    'extractor_params',
    'matcher_params',
}


def launch_tree(colcon_install):
    share = colcon_install / 'lln_ros' / 'share' / 'lln_ros'
    tree = ast.parse((share / 'launch' / 'lln.launch.py').read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    return share, tree, calls


def keywords(call: ast.Call, tree: ast.AST | None = None) -> dict:
    """A call's keywords, with `**name` expanded where `name = dict(...)` is assigned in tree."""
    found = {}
    for kw in call.keywords:
        if kw.arg is None and tree is not None and isinstance(kw.value, ast.Name):
            for node in ast.walk(tree):
                if isinstance(node, ast.Assign) and [getattr(t, 'id', None) for t in node.targets] == [kw.value.id]:
                    found.update(keywords(node.value, tree))
        else:
            found[kw.arg] = kw.value
    return found


def test_launch_arguments(colcon_install):
    _, _, calls = launch_tree(colcon_install)
    declared = {n.args[0].value: keywords(n) for n in calls if n.func.id == 'DeclareLaunchArgument'}
    assert REQUIRED <= set(declared), f'missing launch arguments: {REQUIRED - set(declared)}'
    for name, kw in declared.items():
        assert isinstance(kw.get('description'), (ast.Constant, ast.BinOp, ast.JoinedStr)), name
        default, choices = kw.get('default_value'), kw.get('choices')
        if choices is not None and isinstance(default, ast.Constant):
            assert default.value in [c.value for c in choices.elts], f'{name}: default not among its choices'
    for name in ('use_sim_time', 'verify', 'visualize', 'rviz'):
        assert declared[name]['default_value'].value == 'false'
    assert 'milvus://' in ast.unparse(declared['map_path']['description'])  # any backend URI, not SQLite only


def test_launch_nodes_and_files(colcon_install):
    share, tree, calls = launch_tree(colcon_install)
    lib = colcon_install / 'lln_ros' / 'lib' / 'lln_ros'
    nodes = {keywords(n)['executable'].value: keywords(n, tree) for n in calls if n.func.id == 'Node'}
    assert {'extractor', 'matcher', 'visualizer', 'rviz2'} <= set(nodes)
    for exe in ('extractor', 'matcher', 'visualizer'):
        kw = nodes[exe]
        assert (lib / exe).is_file(), f'ros2 run lln_ros {exe} would not find it'
        assert kw['package'].value == 'lln_ros' and 'namespace' in kw and 'ros_arguments' in kw, exe
        params = ast.unparse(kw['parameters'])
        assert "'use_sim_time': use_sim_time" in params, exe
    assert "'verify': verify" in ast.unparse(nodes['matcher']['parameters'])
    assert "'publish_keypoints': verify" in ast.unparse(nodes['extractor']['parameters'])
    assert "'map_path': LaunchConfiguration('map_path')" in ast.unparse(nodes['matcher']['parameters'])
    source = ast.unparse(tree)
    # the files it names are installed by setup.py's data_files
    assert "'fastdds_large_data.xml'" in source and (share / 'config' / 'fastdds_large_data.xml').is_file()
    assert "'lln.rviz'" in source and (share / 'rviz' / 'lln.rviz').is_file()
    for var in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        assert f"'{var}'" in source


def test_rviz_config_matches_the_nodes(colcon_install):
    """The shipped rviz2 layout parses, uses the visualizer's timeline frame and subscribes topics
    the nodes publish."""
    from lln_ros.nodes.visualizer import PARAMETERS

    share = colcon_install / 'lln_ros' / 'share' / 'lln_ros'
    config = yaml.safe_load((share / 'rviz' / 'lln.rviz').read_text())
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == PARAMETERS['timeline_frame'].default
    displays = {d['Class']: d for d in manager['Displays']}
    assert displays['rviz_default_plugins/MarkerArray']['Topic']['Value'] == 'lln/markers'
    images = [d['Topic']['Value'] for d in manager['Displays'] if d['Class'] == 'rviz_default_plugins/Image']
    assert images == ['lln/overlay', 'lln/activation']
    from lln_ros.ros import topics

    assert displays['rviz_default_plugins/PoseWithCovariance']['Topic']['Value'] == topics.POSE
