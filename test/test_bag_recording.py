"""Opening a recorder's next bag without ROS (:func:`t42_transfer.data.bag.recording.open_next_bag`): a name another
writer took first is passed over, told by the path, not by the words of rosbags' error; any other failure is raised."""

from __future__ import annotations

from pathlib import Path

import pytest
import rosbags.rosbag2.writer as rosbags_writer

from msg_adapters import STRING
from t42_transfer.data.bag.recording import open_next_bag

TYPES = {"/hand/status": STRING}


class Names:
    """``out/bag_000``, ``out/bag_001``, ...: a new name each call, as the recorder's choice counts on past a name
    taken."""

    def __init__(self, out: Path) -> None:
        self.out, self.given = out, 0

    def __call__(self) -> Path:
        self.given += 1
        return self.out / f"bag_{self.given - 1:03d}"


@pytest.fixture
def reworded(monkeypatch: pytest.MonkeyPatch) -> None:
    """rosbags' WriterError in other words than 0.11's ("... exists already, not overwriting.")."""

    class Reworded(rosbags_writer.WriterError):
        def __init__(self, message: str) -> None:
            super().__init__(f"refused: {message.split()[0]}")

    monkeypatch.setattr(rosbags_writer, "WriterError", Reworded)


@pytest.mark.usefixtures("reworded")
def test_a_name_taken_before_the_bag_opens_is_passed_over(tmp_path: Path) -> None:
    (tmp_path / "bag_000").mkdir()  # another recorder on the same out_dir took the name after it was chosen
    writer = open_next_bag(Names(tmp_path), TYPES, {}, {})
    writer.close()
    assert writer.path == tmp_path / "bag_001" and list((tmp_path / "bag_000").iterdir()) == []


@pytest.mark.usefixtures("reworded")
def test_a_name_taken_while_rosbags_opens_the_bag_is_passed_over(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    opened = rosbags_writer.Writer.open

    def other_writer_first(self: rosbags_writer.Writer) -> None:  # between rosbags' check and its mkdir
        if self.path.name == "bag_000":
            self.path.mkdir()
        opened(self)

    monkeypatch.setattr(rosbags_writer.Writer, "open", other_writer_first)
    writer = open_next_bag(Names(tmp_path), TYPES, {}, {})
    writer.close()
    assert writer.path == tmp_path / "bag_001" and list((tmp_path / "bag_000").iterdir()) == []


def test_any_other_failure_to_open_is_raised_at_once(tmp_path: Path) -> None:
    names = Names(tmp_path)
    with pytest.raises(Exception, match="no/SuchType"):  # rosbags knows no such message type
        open_next_bag(names, {"/hand/status": "no/SuchType"}, {}, {})
    assert names.given == 1


def test_the_last_of_the_names_tried_is_raised(tmp_path: Path) -> None:
    for index in range(3):
        (tmp_path / f"bag_{index:03d}").mkdir()
    with pytest.raises(Exception, match="bag_002"):
        open_next_bag(Names(tmp_path), TYPES, {}, {}, tries=3)
