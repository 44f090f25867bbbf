"""``party convert-checkpoint --trust IN OUT``: rewrite a model file as data.

Every loader reads model files with ``torch.load(weights_only=True)``: tensors, plain
containers and torch's allow-listed types, so nothing in a file runs. A file of an older
writer (numpy arrays, whole modules, OmegaConf configs) or a published checkpoint that only a
full unpickle reads is refused; if its owner trusts it, this command unpickles it once (which
runs whatever code the file holds) and writes OUT with the same content as data: numpy arrays
become tensors, numpy scalars numbers, modules their state dicts, configs plain dicts. OUT
loads with ``weights_only=True`` and is written atomically.
"""
from __future__ import annotations

import argparse
import io
import sys
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

USAGE = "party convert-checkpoint --trust IN OUT"


def as_data(x: Any, where: str = "checkpoint") -> Any:
    """``x`` as tensors and plain containers (a TypeError names the first value that is neither)."""
    import numpy as np
    import torch

    if isinstance(x, torch.nn.Module):
        x = x.state_dict()
    if isinstance(x, torch.Tensor):
        return x.detach().clone() if isinstance(x, torch.nn.Parameter) else x
    if isinstance(x, np.ndarray):
        if x.dtype == object:
            return as_data(x.tolist(), where)
        return torch.from_numpy(np.array(x))
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, bytes, int, float, bool, type(None), torch.dtype, torch.device, torch.Size)):
        return x
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
        if isinstance(x, (DictConfig, ListConfig)):
            x = OmegaConf.to_container(x, resolve=True)
    except ImportError:
        pass
    if isinstance(x, Mapping):
        out = OrderedDict() if isinstance(x, OrderedDict) else {}
        for k, v in x.items():
            out[as_data(k, f"{where} key")] = as_data(v, f"{where}[{k!r}]")
        meta = getattr(x, "_metadata", None)       # a state dict's module versions
        if isinstance(out, OrderedDict) and isinstance(meta, Mapping):
            out._metadata = as_data(dict(meta), f"{where}._metadata")
        return out
    if isinstance(x, tuple) and not hasattr(x, "_fields"):
        return tuple(as_data(v, f"{where}[{i}]") for i, v in enumerate(x))
    if isinstance(x, (list, tuple, set, frozenset)):
        return [as_data(v, f"{where}[{i}]") for i, v in enumerate(x)]
    if hasattr(x, "__dict__") and type(x).__name__ in ("Namespace", "SimpleNamespace", "AttributeDict"):
        return as_data(vars(x), where)
    raise TypeError(f"{where}: a {type(x).__module__}.{type(x).__qualname__} is not data "
                    "(tensors, numbers, str, lists, dicts)")


def convert_checkpoint(src: str | Path, dst: str | Path) -> Path:
    """Unpickle ``src`` in full (trusting it: its code runs) and write ``dst`` as data."""
    import torch

    from party.io import require, write_bytes

    src, dst = require(src, USAGE, "checkpoint"), Path(dst)
    try:
        obj = torch.load(src, map_location="cpu", weights_only=False)   # the one trusted unpickle
    except Exception as e:  # name the file whatever torch raised
        raise ValueError(f"{src}: cannot read it as a torch file ({type(e).__name__}: {e})") from e
    try:
        data = as_data(obj)
    except TypeError as e:
        raise ValueError(f"{src}: cannot convert: {e}") from None
    buf = io.BytesIO()
    torch.save(data, buf)
    try:
        torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    except Exception as e:
        raise ValueError(f"{src}: the converted content still does not load with weights_only=True ({e})") from e
    write_bytes(dst, buf.getvalue())
    return dst


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="party convert-checkpoint", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trust", action="store_true",
                        help="confirm that IN comes from a trusted source: unpickling it runs its code")
    parser.add_argument("src", metavar="IN")
    parser.add_argument("dst", metavar="OUT")
    args = parser.parse_args(argv)
    if not args.trust:
        print(f"party convert-checkpoint: {args.src}: not converted. Converting unpickles the file in "
              "full, which runs any code it holds; pass --trust if you trust its source "
              f"(`{USAGE}`)", file=sys.stderr)
        return 2
    try:
        out = convert_checkpoint(args.src, args.dst)
    except (ValueError, FileNotFoundError) as e:
        print(f"party convert-checkpoint: {e}", file=sys.stderr)
        return 1
    print(f"wrote {out} (tensors and plain containers: loads with weights_only=True)")
    return 0
