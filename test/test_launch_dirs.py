"""The directories a suite's transfer server claims for its namespace (t42_transfer.ros.dirs), as `t42 up
--namespace` runs it: in-process, on the test's own ROS domain."""

from __future__ import annotations

from pathlib import Path

import pytest

from t42_transfer.ros.dirs import claim_file


def test_the_transfer_server_claims_the_model_dir_it_uses(ros, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          one_torch_thread: None) -> None:
    """Under /left a relative model_dir `models` is models/left, but the server claimed models/left/left (the
    namespace applied twice): nothing was claimed, and another namespace's suite could take its models.  A model
    directory first made by a transfer's save is claimed then."""
    import t42_transfer.transfer.online as online
    from t42_transfer.nodes.transfer_server import Job, TransferServer

    monkeypatch.chdir(tmp_path)
    (tmp_path / "models" / "left").mkdir(parents=True)  # as after a first run of the /left suite
    (tmp_path / "source.safetensors").write_bytes(b"")
    params = {"source_model": "source.safetensors", "model_dir": "models", "bag_dir": "recordings",
              "progress_period_s": 0.02}
    left = ros.add(TransferServer, params, namespace="/left")
    assert claim_file("models/left").read_text() == "/left\n"
    assert not Path("models/left/left").exists() and not claim_file("models/left/left").exists()

    def first_save_then_fails(spec: online.OnlineTransferSpec, *args: object, **kwargs: object) -> None:
        spec.model_dir.mkdir(parents=True)  # (a save cut short: the directory holds this namespace's files now)
        raise OSError("no space left on device")

    monkeypatch.setattr(online, "run_transfer", first_save_then_fails)
    right = ros.add(TransferServer, params, namespace="/right")
    assert not claim_file("models/right").exists()  # nothing there yet
    outcome = right._run(Job("l2_finetune"))
    assert not outcome.success and "no space left" in outcome.message
    assert claim_file("models/right").read_text() == "/right\n"
    assert left.get_namespace() == "/left"
