"""Shared helpers of the acquisition tests: a mocked real rig file with a short plan, scripted keys."""

import io

import yaml

from tacsplat.acquisition.config import example_rig


def write_mock_rig(folder, **changes) -> str:
    """The shipped mock rig with a plan of 3 train views, 1 test view and 3 grasps (plus ``changes``, by
    top-level section: a mapping updates the section, anything else replaces it), written to ``folder/rig.yaml``."""
    data = yaml.safe_load(example_rig("mock").read_text())
    data["plan"] = {"views": {"train": 3, "test": 1}, "grasps": {"count": 3}}
    for section, values in changes.items():
        if isinstance(values, dict):
            data.setdefault(section, {}).update(values)
        else:
            data[section] = values
    path = folder / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


class ScriptedKeys(io.TextIOBase):
    """Keys handed out one character at a time; ``hooks[i]`` runs just before key ``i`` is read (to inject a
    fault at a known point of the session). No fileno: the session reads it without waiting."""

    def __init__(self, keys: str, hooks: dict | None = None):
        self.keys = keys
        self.hooks = dict(hooks or {})
        self.pos = 0

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> str:
        if self.pos in self.hooks:
            self.hooks.pop(self.pos)()
        out = self.keys[self.pos : self.pos + 1]
        self.pos += len(out)
        return out
