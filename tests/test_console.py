"""The training console's pure parts: the per-epoch line, the loss format, the job's choices."""

import logging

import pytest

from pipeline.console import QUIET_LOGGERS, Console, EpochBar, epoch_line, quiet_ray, short

METRICS = {"epoch": 3, "step": 48, "loss": 6.1e-4, "loss_rec": 5.6e-4, "loss_motion": 0.0712,
           "loss_appearance": 0.0347, "lr": 1e-3, "samples_per_s": 57.6, "data_wait_fraction": 0.1,
           "peak_memory_gb": 0.6, "pmd_seen": 23.21, "pmd_unseen": 22.84}


def test_epoch_line():
    assert epoch_line(METRICS, 6, 31.4) == ("epoch 3/6  loss 6.1e-4 (rec 5.6e-4, motion 7.1e-2, appearance 3.5e-2)"
                                            "  PMD seen 23.2 unseen 22.8  58 samples/s  31 s")


def test_epoch_line_without_pmd():  # a rank that did not evaluate: no PMD column rather than nan
    metrics = {k: v for k, v in METRICS.items() if not k.startswith("pmd")}
    assert epoch_line(metrics, 6, 2.0) == ("epoch 3/6  loss 6.1e-4 (rec 5.6e-4, motion 7.1e-2, appearance 3.5e-2)"
                                           "  58 samples/s  2 s")


@pytest.mark.parametrize("x, text", [(6.1e-4, "6.1e-4"), (0.034, "3.4e-2"), (1.0, "1.0e0"), (123.4, "1.2e2"),
                                     (float("nan"), "nan"), (float("inf"), "inf")])
def test_short(x, text):
    assert short(x) == text


def test_console_for_job(monkeypatch):
    monkeypatch.setattr("sys.stderr.isatty", lambda: True)
    assert Console.for_job().progress
    assert not Console.for_job(no_progress=True).progress
    monkeypatch.setattr("sys.stderr.isatty", lambda: False)
    assert not Console.for_job().progress  # a log file or `ray job logs`: no bar
    assert Console(verbose=True).train_log_level == "INFO" and Console().train_log_level == "WARNING"
    assert Console(**Console(progress=True).to_dict()) == Console(progress=True)  # travels as a dict


def test_quiet_ray_keeps_warnings():
    saved = {name: logging.getLogger(name).level for name in QUIET_LOGGERS}
    try:
        quiet_ray(verbose=True)
        assert {name: logging.getLogger(name).level for name in QUIET_LOGGERS} == saved
        quiet_ray()
        assert not logging.getLogger("ray.data").isEnabledFor(logging.INFO)
        assert logging.getLogger("ray.data").isEnabledFor(logging.WARNING)
        assert logging.getLogger("ray.train.v2").isEnabledFor(logging.WARNING)
        assert logging.getLogger("ray.train").isEnabledFor(logging.ERROR)
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def test_disabled_bar_reads_no_loss():
    bar = EpochBar(False, 1, 2, steps=4, samples_per_step=8)
    bar.step(lambda: pytest.fail("the loss is read only when a bar shows it"))
    bar.close()
