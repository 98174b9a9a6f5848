"""Bad input: valid choices listed, non-zero exit, output paths checked before the run."""

import sys

import pytest

from afvsgp_gym.cli import main

PM = "afvsgp_gym/PointMassObstacle-v0"


def _fails(argv, capsys, code=2):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == code
    cap = capsys.readouterr()
    assert "Episodes" not in cap.out  # nothing ran
    return cap.err


def test_unknown_env_lists_ids(capsys):
    err = _fails(["evaluate", "--env", "afvsgp_gym/Nope-v0"], capsys)
    assert "unknown env id 'afvsgp_gym/Nope-v0'" in err
    assert "afvsgp_gym/FrankaObstacleDynamic-v0" in err and PM in err


def test_unknown_learner_lists_learners(capsys):
    err = _fails(["evaluate", "--env", PM, "--learner", "magic"], capsys)
    assert "unknown learner 'magic'" in err
    for name in ("none", "oracle", "gp", "vsgp", "sogp", "afvsgp"):
        assert name in err
    err = _fails(["evaluate", "--env", PM, "--compare", "none,magic"], capsys)
    assert "unknown learner 'magic' for --compare" in err


def test_unknown_agent_lists_agents(capsys, tmp_path):
    err = _fails(["evaluate", "--env", PM, "--agent", "genius"], capsys)
    assert "unknown agent 'genius'" in err and "nominal" in err and "random" in err
    err = _fails(["evaluate", "--env", PM, "--agent", str(tmp_path / "missing.zip")], capsys)
    assert "does not exist" in err


def test_bad_subcommand_and_algo(capsys):
    _fails(["frobnicate"], capsys)
    err = _fails(["train", "--algo", "dqn", "--env", PM], capsys)
    assert "ppo" in err and "sac" in err
    err = _fails(["bench", "--only", "gp,nope"], capsys)
    assert "gp, envs, filter" in err


@pytest.mark.parametrize("opt", ["--json", "--csv"])
def test_unwritable_output_fails_before_the_run(opt, capsys, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    # 1000 Franka episodes would take hours: the check must come first
    err = _fails(["evaluate", "--env", "afvsgp_gym/FrankaObstacleDynamic-v0", "--episodes",
                  "1000", opt, str(blocker / "x" / "out.json"), "--no-progress"], capsys)
    assert opt in err and "not writable" in err


def test_unwritable_out_dir_for_reproduce_and_video(capsys, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    err = _fails(["reproduce", "--out", str(blocker / "docs")], capsys)
    assert "--out" in err and "not writable" in err
    err = _fails(["video", "--env", PM, "--out", str(blocker / "v.gif")], capsys)
    assert "not writable" in err
    err = _fails(["video", "--env", PM, "--out", str(tmp_path / "v.avi")], capsys)
    assert ".mp4" in err


def test_missing_sb3_names_the_extra(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # import fails as if absent
    err = _fails(["train", "--algo", "ppo", "--env", PM, "--learner", "none"], capsys, code=3)
    assert "afvsgp-gym[rl]" in err
