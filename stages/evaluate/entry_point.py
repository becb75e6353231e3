"""Which `env_entry_point` an evaluation may register with gymnasium.

An entry point names a class (`module:Class`); registering it makes gymnasium import its module and call it, and
importing a module already runs its code. So an entry point is accepted only when it is one of drivesim's own env
classes (the task registry, `sim/envs/registry.py`), or the user opted in with `--trust-entry-point`, or the gymnasium
id is already registered in this process with that same entry point (by code already running here: gymnasium's own
envs, an installed plugin, the caller's Python). Anything else is refused before its module is imported. An accepted
entry point must name a `gymnasium.Env` subclass, checked without calling or instantiating anything.
"""

from __future__ import annotations

import importlib
import inspect
from typing import Any

from drivesim.pipeline.errors import ConfigError
from drivesim.sim.envs.registry import TASKS

TRUST_OPTION = "--trust-entry-point"
ALLOWED_ENTRY_POINTS: frozenset[str] = frozenset(spec.entry_point for spec in TASKS.values())
"""drivesim's own env classes: the entry points an evaluation registers without `--trust-entry-point`."""


def parse_entry_point(text: str) -> tuple[str, str]:
    """(module, attribute path) of `module:Class`; a one-line ValueError when `text` is not of that form."""
    module, sep, attribute = str(text).partition(":")
    names = [*module.split("."), *attribute.split(".")]
    if not sep or not all(name.isidentifier() for name in names):
        raise ValueError(f"{text!r}: give module:Class (a gymnasium.Env subclass), e.g. {min(ALLOWED_ENTRY_POINTS)}")
    return module, attribute


def check_env_id(env_id: str) -> str:
    """`env_id` when it names a gymnasium id alone; a one-line ValueError for `module:Name-v0`, which gymnasium.make
    would import `module` for (running its code) before looking the id up."""
    if ":" in str(env_id):
        raise ValueError(
            f"{env_id!r}: a gymnasium id has no ':' (gymnasium would import the module before it); give the id "
            "alone, and your env's class as env_entry_point"
        )
    return env_id


def env_class(entry_point: str, trusted: bool) -> type:
    """The `gymnasium.Env` subclass `entry_point` names (ConfigError, one line, otherwise).

    An entry point that is not one of drivesim's envs is refused before its module is imported unless `trusted`;
    the class is looked up without running its module's `__getattr__` or any descriptor, and nothing is called.
    """
    import gymnasium

    try:
        module_name, attribute = parse_entry_point(entry_point)
    except ValueError as e:
        raise ConfigError(f"env_entry_point {e}") from None
    if entry_point not in ALLOWED_ENTRY_POINTS and not trusted:
        raise ConfigError(
            f"env_entry_point {entry_point!r} is not one of drivesim's envs ({', '.join(sorted(ALLOWED_ENTRY_POINTS))})"
            f"; to register your own gymnasium.Env class add {TRUST_OPTION} (its module is imported: its code runs)"
        )
    try:
        found: Any = importlib.import_module(module_name)
    except Exception as e:  # whatever the module raises while it is imported (it is the user's own code)
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise ConfigError(f"env_entry_point {entry_point!r}: cannot import {module_name} ({first})") from None
    for name in attribute.split("."):
        try:
            found = inspect.getattr_static(found, name)
        except AttributeError:
            raise ConfigError(f"env_entry_point {entry_point!r}: {module_name} has no {attribute}") from None
    if not (isinstance(found, type) and issubclass(found, gymnasium.Env)):
        raise ConfigError(
            f"env_entry_point {entry_point!r} is a {type(found).__name__}, not a gymnasium.Env subclass; "
            "name your env's class"
        )
    return found


def registered_entry_point(env_id: str) -> str | None:
    """The entry point `env_id` is registered with in this process (as text), None when it is not registered."""
    import gymnasium

    if env_id.startswith("drivesim/"):
        from drivesim.sim.envs.registry import register_envs

        register_envs()
    spec = gymnasium.registry.get(env_id)
    if spec is None:
        return None
    entry = spec.entry_point
    return entry if isinstance(entry, str) else f"{entry.__module__}:{entry.__qualname__}"


def check_env_entry(env_id: str, entry_point: str | None, trust: bool) -> bool:
    """Refuse (ConfigError, one line) an `env_entry_point` this evaluation may not register, before anything of it
    is imported; returns whether the workers may import it (trusted: `trust`, or the id is registered here with it).

    :param env_id: the gymnasium id evaluated in.
    :param entry_point: the config's `env_entry_point` (None: nothing to register).
    :param trust: the user's `--trust-entry-point`.
    """
    if entry_point is None:
        return False
    registered = registered_entry_point(env_id)
    if registered is not None and registered != entry_point:
        raise ConfigError(
            f"env_entry_point {entry_point!r}: {env_id} is registered already (with {registered}); "
            "leave env_entry_point out, or give env_id an id of your own"
        )
    trusted = trust or registered is not None
    env_class(entry_point, trusted)
    return trusted
