"""Names from input files and option lists: unknown names with the closest valid ones, duplicates.

Pure helpers shared by the readers (URDF, robot YAML, CSV, job files) and by `identify`, so that a
typo such as `j2.alpah` is refused with `did you mean 'j2.alpha'?` instead of being ignored.
"""

from __future__ import annotations

import difflib


class UnknownNameError(KeyError, ValueError):
    """A name that is not one of the valid names; the message names it and the closest valid ones.

    A KeyError (as before) and a ValueError (as every other input error), printed without quotes."""

    def __str__(self):
        return str(self.args[0]) if self.args else ""


def closest(name: str, valid, n: int = 3) -> list[str]:
    """Up to n valid names closest to `name` (difflib ratio >= 0.6), best first."""
    return difflib.get_close_matches(str(name), [str(v) for v in valid], n=n, cutoff=0.6)


def suggestion(name: str, valid) -> str:
    """` (did you mean 'a' or 'b'?)` for the closest valid names, or an example of a valid name."""
    hits = closest(name, valid)
    if hits:
        return " (did you mean " + " or ".join(repr(h) for h in hits) + "?)"
    valid = list(valid)
    return f" (valid names look like {valid[0]!r})" if valid else ""


def unknown_names(names, valid) -> list[str]:
    """The entries of `names` that are not in `valid`, in order, each once."""
    ok = set(valid)
    out = []
    for n in names:
        if n not in ok and n not in out:
            out.append(n)
    return out


def check_names(names, valid, what: str) -> None:
    """Raise UnknownNameError naming the first unknown entry of `names` and the closest valid names."""
    bad = unknown_names(names, valid)
    if bad:
        more = f" (and {len(bad) - 1} more unknown: {bad[1:4]})" if len(bad) > 1 else ""
        raise UnknownNameError(f"{what}: unknown name {bad[0]!r}{suggestion(bad[0], valid)}{more}")


def duplicates(names) -> list:
    """Entries that occur more than once, in order of their second occurrence, each once."""
    seen, dup = set(), []
    for n in names:
        if n in seen and n not in dup:
            dup.append(n)
        seen.add(n)
    return dup


__all__ = ["UnknownNameError", "check_names", "closest", "duplicates", "suggestion", "unknown_names"]
