"""benchmarks/car_run.py: the figures of an on-car training, on a log whose answer is known and on a real one."""

import sys

import pytest
from torch.utils.tensorboard import SummaryWriter

import warm_python
from conftest import CAR_TRAIN_FAST, ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import car_run  # noqa: E402


def write_log(run_dir, scalars: dict[str, list[tuple[int, float]]]) -> None:
    writer = SummaryWriter(str(run_dir))
    for tag, series in scalars.items():
        for step, value in series:
            writer.add_scalar(tag, value, step)
    writer.close()


def test_windows_control_counters_and_timing_of_a_known_log(tmp_path, capsys):
    laps = [(900, 14.0), (1000, 13.0), (2000, 12.0), (2000, 15.5), (3000, 11.0), (4000, 10.0)]  # two laps at one log
    control = [(500, 0.2), (1000, 0.6), (1500, 1.0), (2000, 0.995), (2500, 1.0), (3000, 1.0), (4000, 1.0)]
    write_log(tmp_path, {
        "charts/lap_time": laps, "charts/rl_control_fraction": control,
        "charts/control_switches": [(1000, 3.0), (4000, 7.0)], "charts/baseline_regret_per_step": [(1000, 10.0), (4000, 11.075)],
        "loop/period_p50_ms": [(1000, 50.0), (2000, 50.2), (4000, 49.0)], "loop/period_p99_ms": [(1000, 51.0), (2000, 60.0), (4000, 57.0)],
        "link/rtt_p50_ms": [(1000, 0.5)], "loop/frames_dropped": [(1000, 0.0), (4000, 2.0)],
    })  # fmt: skip
    figures = car_run.summarize(car_run.read(tmp_path), [0, 1000, 3000, 4000], control_at=1200)
    # [0, 1000): 14.0; [1000, 3000): 13.0, 12.0, 15.5 (median 13.0, mean 13.5); [3000, 4000] with the last edge: 11.0, 10.0
    assert [(w["laps"], w["median_lap_s"]) for w in figures["windows"]] == [(1, 14.0), (3, 13.0), (2, 10.5)]
    assert figures["control_at"] == (1500, 1.0)  # the first log at or after step 1200
    assert car_run.summarize(car_run.read(tmp_path), [0, 4000], control_at=1000)["control_at"] == (1000, pytest.approx(0.6))  # at: a log on the step
    assert figures["full_control_from"] == 2500  # 100 % at 1500 did not last: 99.5 % is not full control
    assert figures["last"]["control_switches"] == (4000, 7.0)
    assert figures["last"]["baseline_regret_per_step"] == (4000, pytest.approx(11.075))
    assert figures["last"]["fabricated_transitions"] is None and figures["last"]["paired_regret_per_step"] is None
    assert figures["timing"]["loop/period_p50_ms"] == pytest.approx(50.0) and figures["timing"]["loop/period_p99_ms"] == pytest.approx(57.0)
    assert figures["timing"]["link/rtt_p99_ms"] is None and figures["frames_dropped"] == 2.0
    car_run.main([str(tmp_path), "--windows", "0", "1000", "3000", "4000", "--control-at", "1200"])
    out = capsys.readouterr().out
    assert "| median lap time (s) | 14.00 | 13.00 | 10.50 |" in out and "| laps | 1 | 3 | 2 |" in out
    assert "RL control 100 % at step 1,500; 100 % from step 2,500 on" in out
    assert "fabricated_transitions: not logged" in out and "baseline_regret_per_step at step 4,000: 11.1" in out


def test_a_log_that_never_holds_full_control_says_so(tmp_path, capsys):
    write_log(tmp_path, {"charts/rl_control_fraction": [(100, 1.0), (200, 0.5)]})
    figures = car_run.summarize(car_run.read(tmp_path), [0, 1000], control_at=0)
    assert figures["full_control_from"] is None and figures["windows"] == [{"steps": (0, 1000), "laps": 0, "median_lap_s": None}]
    assert "100 % from step – on" in car_run.report(figures)


def test_bad_arguments_are_one_line_errors(tmp_path, capsys):
    for argv, message in (([str(tmp_path)], "holds no TensorBoard events"),
                          ([str(tmp_path), "--windows", "0", "5000", "5000"], "--windows needs two or more increasing edges"),
                          ([str(tmp_path), "--windows", "5000"], "--windows needs two or more increasing edges")):  # fmt: skip
        with pytest.raises(SystemExit) as raised:
            car_run.main(argv)
        assert raised.value.code == 2 and message in capsys.readouterr().err


def test_it_reads_what_a_real_training_logs(tmp_path):
    """The tags it reads are the ones `deploy.jetracer train` writes (laps take longer than a test)."""
    args = ["train", "--total-steps", "60", "--jirl.log-every", "20", "--checkpoint", str(tmp_path / "state.pt"), "--log-dir", str(tmp_path / "runs"), *CAR_TRAIN_FAST]
    out = warm_python.run(["-m", "deploy.jetracer", *args], cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    figures = car_run.summarize(car_run.read(run_dir), [0, 60], control_at=1)
    assert figures["control_at"][0] == 20  # steps 0, 20 and 40 log and 0.0 <= figures["control_at"][1] <= 1.0
    assert all(figures["last"][key][0] == 40 for key in car_run.COUNTERS), figures["last"]
    assert all(value is not None and value > 0 for value in figures["timing"].values()), figures["timing"]
    assert figures["frames_dropped"] is not None
    final = dict(item.rsplit(" ", 1) for item in out.stdout.strip().splitlines()[-1].removeprefix("train: ").split(", "))
    assert figures["last"]["control_switches"][1] <= int(final["control_switches"])  # the run's own line counts to its end
