"""The authors' own saved models: read without running their code, imported faithfully, refused when hostile.

Hand-made files are written here in the authors' legacy torch format by a small
pickle writer of the test's own (the same opcodes their files use), so the import
is checked on every family without the real files; the rollouts are compared with
a reference forward pass written here in numpy (float64, dropout off).  The real
files (../shared/data/authors_models, not redistributed) are checked when present.
"""

from __future__ import annotations

import json
import pickle
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch
from fuzz_harness import DecoderWorker, fuzz, mutated
from safetensors import safe_open

from t42_transfer.cli import main
from t42_transfer.conventions import AUTHORS_ACTION_UNIT_RAD
from t42_transfer.data.errors import DataFileError
from t42_transfer.evaluation.model_files import load_model_file
from t42_transfer.models.authors import AUTHORS_GAMMA, import_authors_model, save_authors_model
from t42_transfer.models.baselines import HoldStill
from t42_transfer.models.checkpoint import UNIT_KEY, load_model
from t42_transfer.models.legacy_torch import AuthorsModelError

AUTHORS_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "authors_models"
MAGIC = 0x1950A86A20F9469CFC6C
TOL_MM = 1e-3

# --------------------------------------------------------------------------- a writer of the authors' format


@dataclass(frozen=True)
class Glob:
    """A global by module and name (``GLOBAL`` opcode)."""

    module: str
    name: str


@dataclass(frozen=True)
class Call:
    """``func(*args)`` (``REDUCE``)."""

    func: object
    args: tuple


@dataclass
class Obj:
    """A module instance as torch pickled it: class record as a persistent id, ``NEWOBJ``, then ``BUILD``."""

    module: str
    name: str
    state: dict


@dataclass
class Store:
    """A float32 storage: its key, and its values (written after the pickles)."""

    key: str
    values: np.ndarray


@dataclass
class Writer:
    """Pickle opcodes for the values above, protocol 2, no memo (the authors' files memoise; nothing depends on it)."""

    storages: list[Store] = field(default_factory=list)

    def emit(self, value: object) -> bytes:
        if value is None:
            return b"N"
        if value is True or value is False:
            return b"\x88" if value else b"\x89"
        if isinstance(value, int):
            assert 0 <= value < 65536
            return b"K" + bytes([value]) if value < 256 else b"M" + struct.pack("<H", value)
        if isinstance(value, float):
            return b"G" + struct.pack(">d", value)
        if isinstance(value, str):
            raw = value.encode()
            return b"X" + struct.pack("<I", len(raw)) + raw
        if isinstance(value, tuple):
            return b")" if not value else b"(" + b"".join(map(self.emit, value)) + b"t"
        if isinstance(value, list):
            return b"]" + (b"(" + b"".join(map(self.emit, value)) + b"e" if value else b"")
        if isinstance(value, dict):
            items = b"".join(self.emit(k) + self.emit(v) for k, v in value.items())
            return b"}" + (b"(" + items + b"u" if value else b"")
        if isinstance(value, Glob):
            return b"c" + value.module.encode() + b"\n" + value.name.encode() + b"\n"
        if isinstance(value, Call):
            return self.emit(value.func) + self.emit(value.args) + b"R"
        if isinstance(value, Obj):
            record = ("module", Glob(value.module, value.name), "/home/x/TrajNet.py", "class ...")
            return self.emit(record) + b"Q" + b")\x81" + self.emit(value.state) + b"b"
        if isinstance(value, Store):
            if value not in self.storages:
                self.storages.append(value)
            return self.emit(("storage", Glob("torch", "FloatStorage"), value.key, "cpu", len(value.values), None)
                             ) + b"Q"
        raise TypeError(type(value))

    def file(self, root: object) -> bytes:
        obj = b"\x80\x02" + self.emit(root) + b"."
        info = {"protocol_version": 1001, "little_endian": True, "type_sizes": {"short": 2, "int": 4, "long": 4}}
        head = b"".join(pickle.dumps(v, protocol=2) for v in (MAGIC, 1001, info))
        keys = pickle.dumps([s.key for s in self.storages], protocol=2)
        data = b"".join(struct.pack("<q", len(s.values)) + s.values.astype("<f4").tobytes() for s in self.storages)
        return head + obj + keys + data


def tensor(values: np.ndarray, key: str, parameter: bool = False) -> Call:
    values = np.asarray(values, np.float32)
    stride = tuple(int(np.prod(values.shape[i + 1:])) for i in range(values.ndim))
    args = (Store(key, values.reshape(-1)), 0, values.shape, stride, False, Call(Glob("collections", "OrderedDict"),
                                                                                    ()))
    rebuilt = Call(Glob("torch._utils", "_rebuild_tensor_v2"), args)
    if parameter:
        return Call(Glob("torch._utils", "_rebuild_parameter"), (rebuilt, True, Call(Glob("collections",
                                                                                          "OrderedDict"), ())))
    return rebuilt


def _module(module: str, name: str, params: dict | None = None, modules: dict | None = None, **attrs: object) -> Obj:
    empty = Call(Glob("collections", "OrderedDict"), ())
    state = {"_backend": Call(Glob("torch.nn.backends.thnn", "_get_thnn_function_backend"), ()),
             "_parameters": {} if params is None else params, "_buffers": empty, "_backward_hooks": empty,
             "_forward_hooks": empty, "_forward_pre_hooks": empty, "_state_dict_hooks": empty,
             "_load_state_dict_pre_hooks": empty, "_modules": {} if modules is None else modules, "training": True,
             **attrs}
    return Obj(module, name, state)


@dataclass
class Net:
    """An MLP's weights: the authors' pt_build_model('1', 10, 4) with hidden width ``hidden``."""

    w: list[np.ndarray]

    @classmethod
    def random(cls, rng: np.random.Generator, hidden: int, scale: float = 0.3) -> Net:
        shapes = ((hidden, 10), (hidden,), (hidden, hidden), (hidden,), (4, hidden), (4,))
        return cls([rng.normal(0, scale / np.sqrt(s[-1] if len(s) == 2 else 4), s).astype(np.float32)
                    for s in shapes])

    def pickled(self, tag: str) -> Obj:
        def linear(i: int, name: str) -> Obj:
            w, b = self.w[2 * i], self.w[2 * i + 1]
            return _module("torch.nn.modules.linear", "Linear",
                           {"weight": tensor(w, f"{tag}{name}w", True), "bias": tensor(b, f"{tag}{name}b", True)},
                           in_features=w.shape[1], out_features=w.shape[0])

        layers = {"0": linear(0, "0"), "1": _module("torch.nn.modules.activation", "SELU", inplace=False),
                  "2": _module("torch.nn.modules.dropout", "AlphaDropout", p=0.1, inplace=False),
                  "3": linear(1, "3"), "4": _module("torch.nn.modules.activation", "Tanh"),
                  "5": _module("torch.nn.modules.dropout", "Dropout", p=0.1, inplace=False), "6": linear(2, "6")}
        return _module("torch.nn.modules.container", "Sequential", modules=layers)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """The forward pass, dropout off, in float64."""
        w = [a.astype(np.float64) for a in self.w]
        h = w[0] @ u + w[1]
        alpha, scale = 1.6732632423543772, 1.0507009873554805
        h = scale * np.where(h > 0, h, alpha * np.expm1(np.minimum(h, 0)))
        h = np.tanh(w[2] @ h + w[3])
        return w[4] @ h + w[5]


@dataclass
class Norm:
    x_mean: np.ndarray
    x_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator) -> Norm:
        """Like the real ones: start-state statistics differ from the state's; actions left as they are."""
        state_mean, state_std = np.array([25.0, 95.0, 75.0, -70.0]), np.array([33.0, 13.8, 64.8, 54.7])
        start_mean = state_mean + rng.normal(0, 5, 4)
        start_std = state_std * rng.uniform(0.3, 0.8, 4)
        return cls(np.r_[state_mean, 0, 0, start_mean].astype(np.float32),
                   np.r_[state_std, 1, 1, start_std].astype(np.float32),
                   rng.normal(0, 0.01, 4).astype(np.float32), np.array([0.1, 0.06, 3.3, 2.8], np.float32))

    def pickled(self, tag: str) -> tuple:
        return tuple(tensor(a, f"{tag}n{i}") for i, a in enumerate((self.x_mean, self.x_std, self.y_mean,
                                                                       self.y_std)))

    def inputs(self, x: np.ndarray, a: np.ndarray, start: np.ndarray) -> np.ndarray:
        return (np.r_[x, a, start] - self.x_mean.astype(np.float64)) / self.x_std.astype(np.float64)

    def delta(self, out: np.ndarray) -> np.ndarray:
        return out * self.y_std.astype(np.float64) + self.y_mean.astype(np.float64)


def trajnet(net: Net, norm: Norm, tag: str, res: Net | None = None, task: str = "transferB2A") -> Obj:
    modules = {"model": net.pickled(tag + "m")}
    attrs = {"task_ofs": 10, "state_dim": 4, "task": task, "action_dim": 6, "dtype": Glob("torch", "float32"),
             "norm": norm.pickled(tag), "reg_loss": None, "coeff": 1}
    if res is None:
        attrs["res"] = None
    else:
        modules["res"] = res.pickled(tag + "r")
    return _module("common.TrajNet", "TrajNet", modules=modules, **attrs)


def cumulative(source: Net, source_norm: Norm, decoder: Net, norm: Norm) -> Obj:
    gru = _module("torch.nn.modules.rnn", "GRU", {"weight_ih_l0": tensor(np.zeros((30, 10)), "g0", True)},
                  mode="GRU", input_size=10, hidden_size=10, num_layers=1)
    encoder_net = _module("common.TrajNet", "LSTMStateTrajNet", modules={"l1": gru}, h=100, norm=norm.pickled("e"))
    encoder = _module("common.TrajNet", "ResBlock", modules={"model": encoder_net}, coeff=0)
    return _module("common.TrajNet", "TimeIndepLatentDeltaNet",
                   modules={"model": trajnet(source, source_norm, "s"), "encoder": encoder,
                            "decoder": trajnet(decoder, norm, "d")},
                   task_ofs=10, state_dim=4, action_dim=6, dtype=Glob("torch", "float32"), norm=norm.pickled("o"),
                   reg_loss=None, internal_state_dim=4, coeff=1)


# --------------------------------------------------------------------------- the reference rollouts (numpy)
def ref_plain(net: Net, norm: Norm, x0: np.ndarray, actions: np.ndarray, res: Net | None = None,
              coeff: float = 1.0) -> np.ndarray:
    """TrajNet.run_traj: z-score [state, action, start], net (+ coeff res), de-normalise, add."""
    x, states = x0.astype(np.float64), [x0.astype(np.float64)]
    for a in actions:
        u = norm.inputs(x, a, x0)
        out = net(u) + (coeff * res(u) if res is not None else 0.0)
        x = x + norm.delta(out)
        states.append(x)
    return np.array(states)


def ref_cumulative(source: Net, source_norm: Norm, decoder: Net, norm: Norm, x0: np.ndarray, actions: np.ndarray,
                   alpha: float, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """LatentDeltaNet.run_traj: the source rolls out alone; g on [x_i, a_i, start] with the outer norm; the sum
    decays by gamma.  Returns (paper alignment: states[i] = x_i + y_i, the authors' alignment: x_i + y_{i+1})."""
    xs = ref_plain(source, source_norm, x0, actions)
    y, ys = np.zeros(4), [np.zeros(4)]
    for x, a in zip(xs[:-1], actions, strict=True):
        y = gamma * y + alpha * norm.delta(decoder(norm.inputs(x, a, x0)))
        ys.append(y)
    ys = np.array(ys)
    return xs + ys, xs[:-1] + ys[1:]


def rollout(model: torch.nn.Module, x0: np.ndarray, actions: np.ndarray) -> np.ndarray:
    return model.rollout(torch.tensor(x0[None], dtype=torch.float32),
                         torch.tensor(actions[None], dtype=torch.float32))[0].double().numpy()


def path(rng: np.random.Generator, steps: int = 400) -> tuple[np.ndarray, np.ndarray]:
    moves = np.array([[1, 1], [-1, -1], [-1, 1], [1, -1], [1.5, 0], [-1.5, 0], [0, 1.5], [0, -1.5]])
    actions = moves[np.repeat(rng.integers(0, 8, steps // 10 + 1), 10)[:steps]]
    return np.array([20.0, 100.0, 80.0, -80.0]), actions


def xy_gap(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a[:, :2] - b[:, :2]).max())


# --------------------------------------------------------------------------- hand-made files, every family
@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict]]:
    """One small file per family and what made it."""
    rng = np.random.default_rng(7)
    root = tmp_path_factory.mktemp("authors")
    parts = {"net": Net.random(rng, 16), "norm": Norm.random(rng), "res": Net.random(rng, 12, 0.05),
             "source": Net.random(rng, 16), "source_norm": Norm.random(rng), "decoder": Net.random(rng, 8, 0.1)}
    trees = {"mlp": trajnet(parts["net"], parts["norm"], "a", task="real_B"),
             "recurrent_residual": trajnet(parts["net"], parts["norm"], "a", res=parts["res"]),
             "cumulative_residual": cumulative(parts["source"], parts["source_norm"], parts["decoder"],
                                               parts["norm"])}
    files = {}
    for family, tree in trees.items():
        files[family] = (root / f"{family}.pkl", parts)
        files[family][0].write_bytes(Writer().file(tree))
    return files


def _reference(family: str, parts: dict, x0: np.ndarray, actions: np.ndarray, negate: bool) -> np.ndarray:
    a = -actions if negate else actions
    if family == "mlp":
        return ref_plain(parts["net"], parts["norm"], x0, a)
    if family == "recurrent_residual":
        return ref_plain(parts["net"], parts["norm"], x0, a, res=parts["res"])
    return ref_cumulative(parts["source"], parts["source_norm"], parts["decoder"], parts["norm"], x0, a, 1.0,
                          AUTHORS_GAMMA)[0]


@pytest.mark.parametrize("negate", [False, True])
@pytest.mark.parametrize("family", ["mlp", "recurrent_residual", "cumulative_residual"])
def test_hand_made_files_roll_out_as_the_authors_forward_pass(made, family, negate):
    file, parts = made[family]
    imported, _ = import_authors_model(file, negate_actions=negate)
    assert imported.family == family
    x0, actions = path(np.random.default_rng(1))
    ours, ref = rollout(imported.model, x0, actions), _reference(family, parts, x0, actions, negate)
    assert np.abs(ref[:, :2]).max() < 1e4 and np.abs(ref[-1, :2] - x0[:2]).max() > 1.0  # it moves, it is finite
    assert xy_gap(ours, ref) < TOL_MM
    assert np.abs(ours[:, 2:] - ref[:, 2:]).max() < 1e-2  # loads (raw units, ~100)


def test_cumulative_residual_differs_from_the_authors_alignment_only_by_one_step(made):
    """Their run_traj adds the residual of step i -> i+1 to state i; the import keeps the paper's alignment."""
    _, parts = made["cumulative_residual"]
    x0, actions = path(np.random.default_rng(2), 200)
    paper, theirs = ref_cumulative(parts["source"], parts["source_norm"], parts["decoder"], parts["norm"], x0,
                                   actions, 1.0, AUTHORS_GAMMA)
    source = ref_plain(parts["source"], parts["source_norm"], x0, actions)
    np.testing.assert_allclose(theirs - source[:-1], paper[1:] - source[1:], atol=1e-9)


def test_alpha_and_gamma_at_rollout_time(made):
    file, parts = made["cumulative_residual"]
    imported, _ = import_authors_model(file, alpha=0.3, gamma=0.9)
    x0, actions = path(np.random.default_rng(3), 200)
    ref = ref_cumulative(parts["source"], parts["source_norm"], parts["decoder"], parts["norm"], x0, actions, 0.3,
                         0.9)[0]
    assert xy_gap(rollout(imported.model, x0, actions), ref) < TOL_MM
    with pytest.raises(AuthorsModelError, match="alpha and gamma apply to residual families only"):
        import_authors_model(made["mlp"][0], gamma=0.9)


def test_the_command_writes_a_checkpoint_naming_the_file_and_family(made, tmp_path, capsys):
    file, parts = made["recurrent_residual"]
    out = tmp_path / "rec.safetensors"
    assert main(["model", "import-authors", str(file), str(out), "--negate-actions"]) == 0
    assert "recurrent_residual" in capsys.readouterr().out
    model, meta = load_model(out)
    import hashlib

    authors = meta["extra"]["authors"]
    assert authors["source_sha256"] == hashlib.sha256(file.read_bytes()).hexdigest()
    assert authors["family"] == "recurrent_residual" and authors["negate_actions"] is True
    assert meta["kind"] == "start_state_recurrent_residual"
    with safe_open(str(out), framework="pt") as f:  # stored, not only the default for an authors' import
        assert json.loads(f.metadata()["t42_transfer"])[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD
    _, on_the_fly = load_model_file(file)  # as experiments and t42 evaluate take a .pkl
    assert on_the_fly[UNIT_KEY] == AUTHORS_ACTION_UNIT_RAD
    x0, actions = path(np.random.default_rng(4), 150)
    assert xy_gap(rollout(model, x0, actions), _reference("recurrent_residual", parts, x0, actions, True)) < TOL_MM
    # never overwrites; a bad file is one line
    assert main(["model", "import-authors", str(file), str(out)]) == 2
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(file.read_bytes()[:500])
    assert main(["model", "import-authors", str(bad), str(tmp_path / "b.safetensors")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and str(bad) in err and not (tmp_path / "b.safetensors").exists()
    with pytest.raises(SystemExit) as exit_info:  # a decay above 1 is refused by the parser
        main(["model", "import-authors", str(file), str(tmp_path / "g.safetensors"), "--gamma", "1.5"])
    assert exit_info.value.code == 2 and "--gamma" in capsys.readouterr().err


def test_saved_model_reloads_to_the_same_rollout(made, tmp_path):
    file, _ = made["cumulative_residual"]
    saved, converted = save_authors_model(file, tmp_path / "c.safetensors")
    model, meta = load_model(saved)
    x0, actions = path(np.random.default_rng(5), 100)
    # the same weights; the reloaded tensors may take another matmul path (float32 rounding only)
    np.testing.assert_allclose(rollout(model, x0, actions), rollout(converted.model, x0, actions), atol=1e-4)
    assert meta["hyperparameters"] == {"negate_actions": False, "alpha": 1.0, "gamma": AUTHORS_GAMMA}


# --------------------------------------------------------------------------- refusals: nothing runs
def _hostile(tmp_path: Path, root: object) -> Path:
    file = tmp_path / "hostile.pkl"
    file.write_bytes(Writer().file(root))
    return file


def _refused(file: Path, match: str) -> str:
    with pytest.raises(AuthorsModelError, match=match) as info:
        import_authors_model(file)
    message = str(info.value)
    assert "\n" not in message and str(file) in message
    return message


@pytest.mark.parametrize("call", [
    lambda marker: Call(Glob("os", "system"), (f"touch {marker}",)),
    lambda marker: Call(Glob("builtins", "open"), (str(marker), "w")),
    lambda marker: Call(Glob("posix", "system"), (f"touch {marker}",)),
    lambda marker: Call(Glob("pathlib", "Path"), (str(marker),)),
])
def test_a_global_that_would_run_code_is_refused_and_nothing_runs(tmp_path, call):
    marker = tmp_path / "ran"
    file = _hostile(tmp_path, call(marker))
    _refused(file, "refused to load global")
    assert not marker.exists()


def test_code_hidden_inside_a_model_object_is_refused(tmp_path, made):
    """The payload sits where a real file keeps an attribute: the model is read as far as the global, no further."""
    marker = tmp_path / "ran"
    _, parts = made["mlp"]
    tree = trajnet(parts["net"], parts["norm"], "a")
    tree.state["reg_loss"] = Call(Glob("os", "system"), (f"touch {marker}",))
    _refused(_hostile(tmp_path, tree), "refused to load global os.system")
    assert not marker.exists()


@pytest.mark.parametrize(("root", "match"), [
    (Glob("torch", "load"), "refused to load global torch.load"),
    (Glob("common.TrajNet", "NBackNet"), "refused to load global common.TrajNet.NBackNet"),
    (Call(Glob("torch.nn.modules.linear", "Linear"), (10, 4)), "refused to call"),
    (Call(Glob("torch._utils", "_rebuild_tensor_v2"), (1, 2, 3, 4, 5, 6)), "a tensor must be"),
    (_module("common.TrajNet", "LSTMStateTrajNet"), "a family this project cannot represent"),
    ({"weights": [1.0, 2.0]}, "not an authors' model object"),
])
def test_what_the_files_never_hold_is_refused_in_one_line(tmp_path, root, match):
    _refused(_hostile(tmp_path, root), match)


def test_a_storage_larger_than_the_file_is_refused_before_any_allocation(tmp_path):
    big = Call(Glob("torch._utils", "_rebuild_tensor_v2"),
               (Store("1", np.zeros(3)), 0, (40000, 40000), (40000, 1), False, {}))
    file = tmp_path / "big.pkl"
    file.write_bytes(Writer().file(big).replace(b"K\x03N", b"M\xff\xffN"))  # declare 65535 elements
    _refused(file, "claim more bytes than the file holds|does not fit its storage")


def test_truncated_and_foreign_files_are_refused_in_one_line(made, tmp_path):
    data = made["mlp"][0].read_bytes()
    for cut in (0, 10, 30, 200, len(data) // 2, len(data) - 4):
        file = tmp_path / f"cut{cut}.pkl"
        file.write_bytes(data[:cut])
        _refused(file, ".")
    other = tmp_path / "norms.pkl"
    other.write_bytes(pickle.dumps({"x": 1}, protocol=2))
    _refused(other, "not a legacy torch file")
    extra = tmp_path / "extra.pkl"
    extra.write_bytes(data + b"\0")
    _refused(extra, "bytes after its last storage")
    _refused(tmp_path, "a directory")
    _refused(tmp_path / "missing.pkl", "does not exist")


# --------------------------------------------------------------------------- the real files
def _real(name: str) -> Path:
    file = AUTHORS_DIR / name
    if not file.is_file():
        pytest.skip(f"the authors' models are not in {AUTHORS_DIR} (public repository schrammlb2/"
                    "Liam-Bayesian-hand-transfer, not redistributed)")
    return file


@pytest.fixture(scope="module")
def hand_a() -> list:
    from t42_transfer.data.t42_real import REAL_FILES, load_t42_testpaths, real_data_dir

    file = real_data_dir() / REAL_FILES["A"]
    if not file.is_file():
        pytest.skip(f"real T42 test paths not found in {file.parent} (set T42_REAL_DATA)")
    return [load_t42_testpaths(file)[i] for i in range(4)]


def _real_parts(file: Path) -> dict:
    """The real file's weights through the importer's reader (its values are plain float32 either way)."""
    from t42_transfer.models.legacy_torch import load_legacy

    legacy = load_legacy(file)

    def net(seq) -> Net:
        mods = seq.state["_modules"]
        return Net([legacy.tensors[mods[k].state["_parameters"][p]].numpy() for k in "036" for p in ("weight",
                                                                                                  "bias")])

    def norm(obj) -> Norm:
        return Norm(*(legacy.tensors[t].numpy() for t in obj.state["norm"]))

    root = legacy.root
    if root.cls.endswith("TimeIndepLatentDeltaNet"):
        src, dec = root.state["_modules"]["model"], root.state["_modules"]["decoder"]
        return {"source": net(src.state["_modules"]["model"]), "source_norm": norm(src),
                "decoder": net(dec.state["_modules"]["model"]), "norm": norm(root)}
    res = root.state["_modules"].get("res")
    return {"net": net(root.state["_modules"]["model"]), "norm": norm(root), "res": res and net(res)}


@pytest.mark.realdata
@pytest.mark.parametrize(("name", "family"), [
    ("real_B_heldout0.1_1.pkl", "mlp"),
    ("transferB2A_traj_transfer_timeless_recurrent_heldout0.9_10.pkl", "recurrent_residual"),
    ("transferB2A_traj_transfer_timeless_heldout0.9_10.pkl", "cumulative_residual"),
])
def test_real_files_roll_out_as_the_authors_forward_pass_on_a_hand_a_path(hand_a, name, family):
    file = _real(name)
    imported, _ = import_authors_model(file, negate_actions=True)
    assert imported.family == family
    episode = hand_a[1]  # 1248 steps
    x0, actions = episode.states[0].astype(np.float64), episode.actions.astype(np.float64)
    ref = _reference(family, _real_parts(file), x0, actions, negate=True)
    assert xy_gap(rollout(imported.model, x0, actions), ref) < TOL_MM


def _divergence(model: torch.nn.Module, episodes: list, threshold: float = 4.0) -> float:
    steps = []
    for e in episodes:
        err = np.linalg.norm(rollout(model, e.states[0], e.actions)[:, :2] - e.states[:, :2], axis=1)
        over = np.nonzero(err > threshold)[0]
        steps.append(int(over[0]) if len(over) else len(err))
    return float(np.mean(steps))


@pytest.mark.realdata
def test_real_files_reproduce_the_readmes_reference_figures(hand_a):
    """Hold still 61; B direct (actions negated) 702; naive fine-tuning at h = 0.997: 268 (5 repeats)."""
    direct, _ = import_authors_model(_real("real_B_heldout0.1_1.pkl"), negate_actions=True)
    assert abs(_divergence(HoldStill(), hand_a) - 61) <= 3
    assert abs(_divergence(direct.model, hand_a) - 702) <= 3
    naive = [_divergence(import_authors_model(_real(f"transferB2A_retrain_naive_heldout0.997_{r}.pkl"),
                                              negate_actions=True)[0].model, hand_a) for r in range(10, 15)]
    assert abs(np.mean(naive) - 268) <= 3


def test_every_real_file_imports():
    files = sorted(_real("real_B_heldout0.1_1.pkl").parent.glob("*.pkl"))
    families = {}
    for file in files:
        families.setdefault(import_authors_model(file)[0].family, []).append(file.name)
    assert {k: len(v) for k, v in families.items()} == {"mlp": 122, "recurrent_residual": 40,
                                                        "cumulative_residual": 40}


# --------------------------------------------------------------------------- fuzzing the reader
@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    keep = tmp_path_factory.mktemp("authors-escapes")
    target = "t42_transfer.models.authors:import_authors_model"
    with DecoderWorker(target, errors="t42_transfer.data.errors:DataFileError", mem_mb=256, timeout_s=10,
                       keep_dir=keep) as w:
        yield w


def _seeds(made) -> list[bytes]:
    return [made[f][0].read_bytes() for f in ("mlp", "recurrent_residual", "cumulative_residual")]


def _fuzz(worker: DecoderWorker, made, examples: int) -> dict[str, int]:
    from hypothesis import strategies as st

    counts = fuzz(worker, st.sampled_from(_seeds(made)).flatmap(mutated), "model.pkl", examples)
    assert sum(counts.values()) >= examples
    return counts


def test_the_seeds_are_accepted_by_the_worker(worker, made):
    for data in _seeds(made):
        assert worker.check_bytes(data, "model.pkl").outcome == "accepted"


def test_mutated_files_fast_slice(worker, made):
    _fuzz(worker, made, 30)


@pytest.mark.slow
def test_mutated_files(worker, made):
    counts = _fuzz(worker, made, 2000)
    assert counts["refused"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["real_B_heldout0.1_1.pkl", "transferB2A_traj_transfer_timeless_heldout0.9_10.pkl"])
def test_mutated_real_files(worker, name):
    counts = fuzz(worker, mutated(_real(name).read_bytes()), "model.pkl", 300)
    assert sum(counts.values()) >= 300


def test_error_class_is_the_projects():
    assert issubclass(AuthorsModelError, DataFileError)
