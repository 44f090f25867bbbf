"""What a part-text backend returns for one caption."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class PartTextResult:
    parts: dict                  # {part: str} for every part of part_texts.parts
    fallback: bool = False       # True: the answer is the fallback (format never valid / request failed)
    reason: str = ""             # why it fell back ("format: ...", "request: ...")
    calls: int = 0               # requests sent to the backend (rules: 1 per caption)
    retries: int = 0             # requests re-sent after 429/5xx/timeouts/connection errors
    format_failures: int = 0     # answers that failed the format check
    raw: str = ""                # the last raw answer (for inspection in the cache)
    cacheable: bool = True       # False: a transient failure; do not store, ask again next run
    extra: dict = field(default_factory=dict)


class BackendError(RuntimeError):
    """A failure that retrying will not fix (bad URL/model/key): the stage stops."""
