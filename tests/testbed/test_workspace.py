"""Only physically possible acquisitions: every view and sweep pose is checked against the
robot, the C-arm, the table, the patient and the instruments before any simulation."""

import pytest

from testbed.scene import find_scene, load_scene, parse_scene
from testbed.simulate import case_world
from testbed.workspace import WorkspaceError, check_scene_workspace, require_feasible


def _turned(name="experiment2", view=1, **update):
    d = load_scene(find_scene(name)).model_dump(mode="json")
    d["views"][view].update(update)
    return parse_scene(d, source="turned.toml")


@pytest.mark.parametrize("name", ["experiment1", "experiment2", "experiment2-ideal"])
def test_shipped_scenes_are_feasible(name):
    scene, world = case_world(load_scene(find_scene(name)), 0)
    reports = check_scene_workspace(scene, world)
    assert len(reports) == len(scene.views)
    assert all(r.ok for r in reports), [r.summary() for r in reports]
    assert all(len(r.poses) >= 10 for r in reports)


def test_a_view_turned_into_the_robot_is_refused_naming_view_pose_and_pair():
    # the paper's oblique turned towards the robot: the quill and wrist hit the C-arm
    scene, world = case_world(_turned(angular_deg=-35.0, orbital_deg=8.0), 0)
    with pytest.raises(WorkspaceError) as err:
        require_feasible(scene, world)
    msg = str(err.value)
    assert "\n" not in msg
    assert "view proximal_oblique" in msg and "sweep pose" in msg
    assert "collides with carm_" in msg and "robot_" in msg
    # opting out skips the check
    d = scene.model_dump(mode="json")
    d["workspace"]["check"] = False
    assert require_feasible(parse_scene(d), world) == []


def test_an_unreachable_robot_is_refused_before_the_simulation(capsys):

    d = load_scene(find_scene("experiment2")).model_dump(mode="json")
    d["robot"]["link1_mm"] = d["robot"]["link2_mm"] = 1.0
    scene, world = case_world(parse_scene(d), 0)
    with pytest.raises(WorkspaceError, match="unreachable"):
        require_feasible(scene, world)


def test_run_on_a_colliding_scene_exits_2_with_one_line(tmp_path, capsys):
    import tomllib

    from studies.cli import main

    text = find_scene("experiment2").read_text()
    d = tomllib.loads(text)
    assert d["views"][1]["name"] == "proximal_oblique"
    bad = text.replace("orbital_deg = 10.0\nangular_deg = 28.0",
                       "orbital_deg = 8.0\nangular_deg = -35.0")
    assert bad != text
    f = tmp_path / "colliding.toml"
    f.write_text(bad)
    assert main(["run", str(f)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if "pybullet" not in ln]
    assert len(err) == 1
    assert "view proximal_oblique, sweep pose" in err[0] and "collides with" in err[0]
