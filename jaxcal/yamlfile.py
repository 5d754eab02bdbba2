"""YAML read strictly: a key given twice in one mapping is an error (PyYAML silently keeps the last).

`load_yaml(data)` returns the document like `yaml.safe_load`; a duplicate key raises
`DuplicateKeyError` (a `yaml.YAMLError`) naming the key and both lines. Readers wrap it into their
own error type (RobotFileError, ConfigError) as they do for any YAML syntax error.
"""

from __future__ import annotations

import yaml


class DuplicateKeyError(yaml.YAMLError):
    """A mapping that gives the same key twice."""


class StrictLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses duplicate keys in a mapping."""


def _construct_mapping(loader, node, deep=False):
    loader.flatten_mapping(node)
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            continue  # an unhashable key: the base constructor reports it
        if key in seen:
            raise DuplicateKeyError(f"key {key!r} given twice (lines {seen[key] + 1} and {key_node.start_mark.line + 1}); "
                                    "only one value is allowed")
        seen[key] = key_node.start_mark.line
    return yaml.SafeLoader.construct_mapping(loader, node, deep)


StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml(data):
    """The document of a YAML text (str or bytes) or stream; duplicate keys raise DuplicateKeyError."""
    return yaml.load(data, Loader=StrictLoader)  # noqa: S506 (a SafeLoader subclass)


__all__ = ["DuplicateKeyError", "StrictLoader", "load_yaml"]
