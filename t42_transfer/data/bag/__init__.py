"""rosbag2 bags <-> TrajectorySet, in the hand wire format of :mod:`msg_adapters`.

One module per job: :mod:`.writer` writes bags, :mod:`.steps` groups arriving messages into steps, :mod:`.recording`
keeps a recorder's bag bookkeeping (free names, a removed file, log times after a clock restart, pauses),
:mod:`.storage` reads storage files (MCAP record by record, sqlite3 through :mod:`.db3`'s rosbags reader, which
:mod:`.playback` opens bags with too), :mod:`.idl` puts rosbag2's IDL definitions in the form rosbags reads,
:mod:`.metadata` parses ``metadata.yaml`` and ``custom_data``,
:mod:`.episodes` turns hand messages into episodes, :mod:`.reader` reads a bag whole, :mod:`.playback` opens one
to play in time order and paces it, and :mod:`.repair` rewrites a killed writer's bag.  The names here are the
package's public API.
"""

from t42_transfer.data.bag.episodes import EPISODE_GAP_NS, EPISODE_GAP_S
from t42_transfer.data.bag.hand_topics import hand_namespace
from t42_transfer.data.bag.metadata import EPISODES_KEY, HAND_KEY, REPAIRED_KEY
from t42_transfer.data.bag.reader import bag_info, declared_bag_unit, read_bag, verify_bag
from t42_transfer.data.bag.storage import is_bag, list_bags
from t42_transfer.data.bag.writer import (
    DEFAULT_T0_NS,
    RECORD_QOS,
    ROS_DISTRO,
    BagWriter,
    JazzyWriter,
    assign_start_times,
    write_bag,
)
from t42_transfer.data.errors import BagError

__all__ = [
    "DEFAULT_T0_NS", "EPISODES_KEY", "EPISODE_GAP_NS", "EPISODE_GAP_S", "HAND_KEY", "RECORD_QOS", "REPAIRED_KEY",
    "ROS_DISTRO", "BagError", "BagWriter", "JazzyWriter", "assign_start_times", "bag_info", "declared_bag_unit",
    "hand_namespace", "is_bag", "list_bags", "read_bag", "verify_bag", "write_bag",
]
