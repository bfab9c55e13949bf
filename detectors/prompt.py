"""Text prompt augmentation (FM-Fusion Sec. III-B): q^t = tags^t ∪ U^t.

U^t is the set of labels detected in the previous `window` detection frames (5 in the paper), without the
excluded labels (floor, carpet, door, glass door, window, fridge, refrigerator: large or ambiguous labels that
would be proposed everywhere). The exclusion only stops augmentation from adding a label: a label the
tagger itself produced this frame stays in the prompt.

Use: per detection frame, ``prompt = augmenter.prompt(frame_name, tags)``, detect with it, then
``augmenter.observe(detected_labels)``. A frame that is never observed counts as having detected nothing.
`history` records every frame's prompt; `reset()` starts a new sequence.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Iterable, Sequence


@dataclasses.dataclass(frozen=True)
class PromptRecord:
    """One frame's prompt: the tagger's `tags`, the labels `added` by augmentation, and the `prompt` sent."""

    frame_name: str
    tags: tuple[str, ...]
    added: tuple[str, ...]
    prompt: tuple[str, ...]


class PromptAugmenter:
    """Stateful prompt augmentation over a sequence of detection frames.

    Args:
      window: how many previous detection frames lend their detected labels (0 turns augmentation off).
      excluded: labels never added by augmentation.
      open_labels: the labels of interest; only these are added, in this order. None: any label, sorted.
    """

    def __init__(self, window: int = 5, excluded: Iterable[str] = (), open_labels: Sequence[str] | None = None):
        if window < 0:
            raise ValueError(f"prompt augmentation window {window} must be >= 0")
        self.window = window
        self.excluded = frozenset(excluded)
        self.open_labels = tuple(open_labels) if open_labels is not None else None
        self.history: list[PromptRecord] = []
        self._recent: collections.deque[frozenset[str]] = collections.deque(maxlen=window or None)
        self._pending = False

    def reset(self) -> None:
        """Forgets the previous frames (a new sequence)."""
        self.history.clear()
        self._recent.clear()
        self._pending = False

    def candidates(self) -> list[str]:
        """U^t: labels detected in the last `window` observed frames, minus the excluded ones, ordered."""
        if self.window == 0:
            return []
        recent = set().union(*self._recent) - self.excluded
        if self.open_labels is not None:
            return [label for label in self.open_labels if label in recent]
        return sorted(recent)

    def prompt(self, frame_name: str, tags: Sequence[str]) -> list[str]:
        """The prompt of this frame: its tags (in order), then the augmentation labels not among them."""
        if self._pending:
            self.observe(())
        tags = list(dict.fromkeys(tags))
        added = [label for label in self.candidates() if label not in tags]
        prompt = tags + added
        self.history.append(PromptRecord(frame_name, tuple(tags), tuple(added), tuple(prompt)))
        self._pending = True
        return prompt

    def observe(self, detected_labels: Iterable[str]) -> None:
        """Records the labels detected with the last prompt (every label of every detection)."""
        if self.window:
            self._recent.append(frozenset(detected_labels))
        self._pending = False
