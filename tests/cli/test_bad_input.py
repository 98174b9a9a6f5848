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


#: (argv, what stderr must name): each is refused with exit status 2 before anything runs.
#: ``{tmp}`` is a fresh folder holding ``empty.jsonl`` (no record), ``bad.toml`` (not TOML)
#: and ``nothing/`` (an empty folder).
BAD_ARGUMENTS = [
    ([], "the following arguments are required: COMMAND"),
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["evaluate", "--episodes", "0"], "--episodes: expected a positive integer, got 0"),
    (["evaluate", "--episodes", "-1"], "--episodes: expected a positive integer, got -1"),
    (["evaluate", "--episodes", "abc"], "--episodes: expected a positive integer, got 'abc'"),
    (["evaluate", "--max-steps", "0"], "--max-steps: expected a positive integer"),
    (["evaluate", "--workers", "0"], "--workers: expected a positive integer"),
    (["evaluate", "--seed", "x"], "--seed: invalid int value: 'x'"),
    (["evaluate", "--env", PM, "--env-kwargs", "[1]"], "--env-kwargs must be a JSON object"),
    (["evaluate", "--env", PM, "--filter-kwargs", "{bad"], "--filter-kwargs must be a JSON"),
    (["evaluate", "--env", PM, "--env-kwargs", '{"mass": -1}'], "--env-kwargs: ValueError: mass"),
    (["evaluate", "--env", PM, "--env-kwargs", '{"colour": 1}'], "colour"),
    (["evaluate", "--env", PM, "--filter-kwargs", '{"beta": -1}'],
     "--filter-kwargs: ValueError: beta"),
    (["evaluate", "--env", PM, "--filter-kwargs", '{"activation_distance": -0.1}'],
     "activation_distance must be >= 0"),
    (["evaluate", "--env", PM, "--filter-kwargs", '{"learner_kwargs": {"num_inducing": 0}}'],
     "num_inducing must be an integer >= 1"),
    (["evaluate", "--env", PM, "--compare", ","], "--compare needs a comma-separated list"),
    (["report", "{tmp}/empty.jsonl"], "empty.jsonl holds no finished episode"),
    (["report", "{tmp}/missing.jsonl"], "cannot read results"),
    (["report", "{tmp}/empty.jsonl", "--confidence", "1.5"], "--confidence must be in (0, 1)"),
    (["report", "{tmp}/empty.jsonl", "--confidence", "0"], "--confidence must be in (0, 1)"),
    (["report", "{tmp}/empty.jsonl", "--confidence", "abc"], "invalid float value: 'abc'"),
    (["sweep", "{tmp}/missing.toml"], "cannot read config"),
    (["sweep", "{tmp}/bad.toml"], "not valid TOML"),
    (["sweep", "{tmp}/bad.toml", "--limit", "0"], "--limit: expected a positive integer"),
    (["sweep", "{tmp}/bad.toml", "--workers", "-2"], "--workers: expected a positive integer"),
    (["train", "--timesteps", "0"], "--timesteps: expected a positive integer"),
    (["train", "--algo", "dqn"], "invalid choice: 'dqn'"),
    (["train", "--env", PM, "--learner", "none", "--out", "{tmp}/a.zip", "--algo-kwargs", "[1]"],
     "--algo-kwargs must be a JSON object"),
    (["video", "--every", "0"], "--every: expected a positive integer"),
    (["video", "--env", PM, "--env-kwargs", '{"mass": 0}', "--out", "{tmp}/v.gif"],
     "--env-kwargs: ValueError: mass"),
    (["plot", "--traces", "{tmp}/nothing"], "no traces file"),
    (["bench", "--only", "nope"], "unknown benchmark area(s) ['nope']"),
]


@pytest.mark.parametrize(("argv", "message"), BAD_ARGUMENTS,
                         ids=[" ".join(a) or "(none)" for a, _ in BAD_ARGUMENTS])
def test_bad_arguments_exit_with_status_2(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", object())  # train's check passes
    (tmp_path / "empty.jsonl").write_text("")
    (tmp_path / "bad.toml").write_text("grid = [")
    (tmp_path / "nothing").mkdir()
    err = _fails([a.replace("{tmp}", str(tmp_path)) for a in argv], capsys)
    assert message in err
    assert not (tmp_path / "a.zip").exists() and not (tmp_path / "v.gif").exists()
