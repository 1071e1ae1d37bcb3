"""Index ranges as people type them on a command line: `0-7`, `0,3,5`, `0-3,8`.

Agents (`hammer local --agents`), seeds (`hammer sweep --seeds`, `hammer train --seeds`) and
evaluation seeds are all written this way; one parser keeps them behaving alike. It lives on the
lowest floor because the roles (agent pools) and the learning code both need it.
"""

from __future__ import annotations


def parse_indices(text: str, option: str, upper: int | None = None, what: str = "index") -> list[int]:
    """`0-3,8` -> [0, 1, 2, 3, 8]: sorted, distinct, each >= 0 (and < `upper` when given). A ValueError
    names the option, the part at fault and a fix, in one line."""
    example = f"e.g. {option} 0-7 or {option} 0,2,5-7"
    out: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        lo, dash, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise ValueError(f"{option} {text!r}: {part!r} is not an {what} or a range FIRST-LAST; fix: {example}") \
                from None
        if first < 0 or last < first:
            raise ValueError(f"{option} {text!r}: range {part!r} must be FIRST-LAST with 0 <= FIRST <= LAST; "
                             f"fix: {example}")
        out.update(range(first, last + 1))
    if upper is not None and max(out) >= upper:
        raise ValueError(f"{option} {text!r}: there are only {upper} ({what} 0..{upper - 1}); fix: {example}")
    return sorted(out)
