"""Another checkout's runtime and codec as modules of their own, for an A/B in one run
(bench/hop.py and bench/inbox_cost.py --baseline DIR)."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_module(tree: str, relative: str, name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, Path(tree) / relative)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module   # dataclasses look their module up while it runs
    spec.loader.exec_module(module)
    return module


def baseline_message(tree: str, message):
    """`message` (this tree's definition) compiled by DIR/schemas/core.py's codec."""
    core = load_module(tree, "schemas/core.py", "baseline_schemas_core")
    fields = tuple(core.Field(**dataclasses.asdict(f)) for f in message.fields)
    known = {f.name for f in dataclasses.fields(core.Message)} - {"fields", "_by_name"}
    kwargs = {k: getattr(message, k) for k in known if not k.startswith("_")}
    return core.Message(fields=fields, **kwargs)
