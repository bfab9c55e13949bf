"""Loading ONNX files into onnxruntime sessions and checking them against their contract.

`OnnxModel(path, contract, providers)` opens the file (a missing file is a `ModelNotFoundError` naming the
path and how to export it), binds each contract tensor to the file's name for it (aliases allowed) and
checks ranks, fixed sizes and element types; any mismatch is a `ContractError` listing what was expected
and what the file has. `run` then takes and returns tensors by their contract names.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from detectors.contracts import ORT_TYPES, ModelContract, TensorSpec
from fmfusion_jax.errors import DataError, UserError

logger = logging.getLogger(__name__)

_NUMPY_TYPES = {
    "float32": np.float32,
    "float16": np.float16,
    "int64": np.int64,
    "int32": np.int32,
    "bool": np.bool_,
    "uint8": np.uint8,
}
_NAMES_BY_ORT = {ort: name for name, ort in ORT_TYPES.items()}

CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"


class ModelNotFoundError(UserError):
    """A model file (or its vocabulary) is missing; the message names it and says how to make it."""


class ContractError(UserError):
    """An ONNX file does not match its contract; the message lists the expected and the found tensors."""


@dataclasses.dataclass(frozen=True)
class BoundTensor:
    """A contract tensor as the file has it: its name there, dims (int, or None when free) and element type."""

    spec: TensorSpec
    name: str
    shape: tuple[int | None, ...]
    dtype: str

    @property
    def numpy_dtype(self) -> type:
        return _NUMPY_TYPES[self.dtype]


def available_providers() -> list[str]:
    import onnxruntime

    return list(onnxruntime.get_available_providers())


def resolve_providers(providers: str | Sequence[str] = "cpu") -> list[str]:
    """onnxruntime provider names for ``"cpu"``, ``"cuda"``, ``"auto"`` or an explicit list.

    ``"cuda"`` when onnxruntime has no CUDAExecutionProvider (the CPU wheel, no GPU) falls back to the CPU
    with a warning; ``"auto"`` takes CUDA when available, silently. CPU always comes last as the fallback.
    """
    if isinstance(providers, str):
        choice = providers.lower()
        if choice not in ("cpu", "cuda", "auto"):
            raise UserError(f"providers {providers!r}: expected 'cpu', 'cuda', 'auto' or a list of onnxruntime provider names")
        if choice == "cpu":
            return [CPU]
        if CUDA in available_providers():
            return [CUDA, CPU]
        if choice == "cuda":
            logger.warning(
                "CUDAExecutionProvider is not available in this onnxruntime (available: %s); using the "
                "CPU (install onnxruntime-gpu for CUDA)",
                ", ".join(available_providers()),
            )
        return [CPU]
    names = list(providers)
    unknown = [name for name in names if name not in available_providers()]
    if unknown:
        raise UserError(f"onnxruntime providers {unknown} are not available here (available: {', '.join(available_providers())})")
    return names if CPU in names else [*names, CPU]


def require_file(path: Path, what: str, how: str) -> Path:
    """`path` if it is a file, else `ModelNotFoundError` saying what it is and how to make it."""
    if not path.is_file():
        where = "folder missing" if not path.parent.is_dir() else "not found"
        raise ModelNotFoundError(f"{path}: {what} {where}. {how} (see docs/detectors.md).")
    return path


def open_session(path: Path, contract: ModelContract, providers: str | Sequence[str] = "cpu", threads: int | None = None):
    """An onnxruntime session of `path` (`threads` intra-op threads, or onnxruntime's default).

    A missing file is a `ModelNotFoundError` saying how to make it; a file onnxruntime cannot load a `DataError`.
    """
    import onnxruntime

    require_file(path, f"{contract.title} model", f"Export it to {contract.filename}: {contract.export_hint}")
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    if threads:
        options.intra_op_num_threads = threads
    try:
        return onnxruntime.InferenceSession(str(path), sess_options=options, providers=resolve_providers(providers))
    except UserError:
        raise
    except Exception as error:  # onnxruntime raises its own pybind exception types
        raise DataError(f"{path}: onnxruntime cannot load this {contract.title} model ({error})") from None


class OnnxModel:
    """An onnxruntime session checked against a `ModelContract`.

    Attributes:
      path: the ONNX file.
      contract: what it must look like.
      inputs, outputs: contract name -> `BoundTensor` (outputs only for those the file has).
      dims: free dimension name -> size, for those the file fixes (e.g. ``num_tokens`` -> 256).
      providers: the providers the session runs on.
    """

    def __init__(
        self,
        path: str | Path,
        contract: ModelContract,
        providers: str | Sequence[str] = "cpu",
        threads: int | None = None,
        session=None,
    ):
        self.path = Path(path)
        self.contract = contract
        # An open `session` of `path` is bound as it is (a caller choosing among contracts loads the file once).
        self.session = session or open_session(self.path, contract, providers, threads)
        self.providers = self.session.get_providers()
        self.inputs, self.outputs, self.dims = bind_contract(self.session, contract, self.path)

    def __repr__(self) -> str:
        return f"OnnxModel({str(self.path)!r}, {self.contract.key}, providers={self.providers})"

    def has_input(self, name: str) -> bool:
        return name in self.inputs

    def has_output(self, name: str) -> bool:
        return name in self.outputs

    def run(self, feeds: Mapping[str, np.ndarray], outputs: Sequence[str]) -> dict[str, np.ndarray]:
        """Runs the session on `feeds` (contract names; cast to the file's types); returns `outputs` by name.

        Floating outputs come back as float32.
        """
        session_feeds: dict[str, np.ndarray] = {}
        for name, value in feeds.items():
            bound = self.inputs[name]
            session_feeds[bound.name] = np.ascontiguousarray(np.asarray(value).astype(bound.numpy_dtype, copy=False))
        names = [self.outputs[name].name for name in outputs]
        results = self.session.run(names, session_feeds)
        out = {}
        for name, value in zip(outputs, results):
            value = np.asarray(value)
            out[name] = value.astype(np.float32) if value.dtype == np.float16 else value
        return out


def bind_contract(
    session, contract: ModelContract, path: Path
) -> tuple[dict[str, BoundTensor], dict[str, BoundTensor], dict[str, int]]:
    """Matches a session's inputs and outputs to `contract`; `ContractError` listing every problem."""
    problems: list[str] = []
    dims: dict[str, int] = {}
    session_inputs = {arg.name: arg for arg in session.get_inputs()}
    session_outputs = {arg.name: arg for arg in session.get_outputs()}

    def bind(specs, available, kind) -> dict[str, BoundTensor]:
        bound = {}
        for spec in specs:
            matches = [name for name in spec.names if name in available]
            if not matches:
                if spec.required:
                    problems.append(f"{kind} {spec.name!r} missing")
                continue
            if len(matches) > 1:
                problems.append(f"{kind} {spec.name!r} present under several names {matches}")
                continue
            arg = available[matches[0]]
            shape = tuple(d if isinstance(d, int) and d > 0 else None for d in (arg.shape or ()))
            dtype = _NAMES_BY_ORT.get(arg.type, arg.type)
            where = f"{kind} {arg.name!r}"
            if dtype not in spec.dtypes:
                problems.append(f"{where} has element type {dtype}, expected {' or '.join(spec.dtypes)}")
            if len(shape) != len(spec.shape):
                problems.append(
                    f"{where} has rank {len(shape)} {_dims(arg.shape)}, expected rank {len(spec.shape)} {_dims(spec.shape)}"
                )
            else:
                for axis, (want, have) in enumerate(zip(spec.shape, shape)):
                    if have is None:
                        continue
                    if isinstance(want, int) and want != have:
                        problems.append(f"{where} has size {have} on axis {axis}, expected {want}")
                    elif isinstance(want, str):
                        if dims.setdefault(want, have) != have:
                            problems.append(
                                f"{where} has {want} = {have} on axis {axis}, but another tensor has {want} = {dims[want]}"
                            )
            bound[spec.name] = BoundTensor(spec, arg.name, shape, dtype)
        return bound

    inputs = bind(contract.inputs, session_inputs, "input")
    outputs = bind(contract.outputs, session_outputs, "output")
    used = {b.name for b in inputs.values()}
    for name in session_inputs:
        if name not in used:
            problems.append(f"input {name!r} is not one the front end can feed")
    for group in contract.one_of:
        if not any(name in outputs for name in group):
            problems.append(f"none of the outputs {list(group)}")
    if problems:
        found = ["  found inputs:"] + [f"    {_describe_arg(arg)}" for arg in session.get_inputs()]
        found += ["  found outputs:"] + [f"    {_describe_arg(arg)}" for arg in session.get_outputs()]
        raise ContractError(
            f"{path}: does not match the {contract.title} contract (mirrors {contract.mirrors}):\n"
            + "\n".join(f"  - {p}" for p in problems)
            + "\n"
            + contract.describe()
            + "\n"
            + "\n".join(found)
            + f"\n  How to make a matching file: {contract.export_hint} (see docs/detectors.md)."
        )
    return inputs, outputs, dims


def _dims(shape) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in (shape or ())) + "]"


def _describe_arg(arg) -> str:
    return f"{arg.name} {_dims(arg.shape)} {_NAMES_BY_ORT.get(arg.type, arg.type)}"
