"""A minimal BERT WordPiece tokenizer and GroundingDINO's caption encoding.

GroundingDINO reads its text through bert-base-uncased, so the front end must produce the same token ids
as BERT's uncased tokenizer: the `vocab.txt` of bert-base-uncased sits beside the ONNX file and this module
implements the published algorithm (no `transformers` dependency):

1. basic tokenization: drop control characters, map whitespace to spaces, put spaces around CJK
   characters, split on whitespace, lower-case, strip accents (NFD, drop combining marks), split every
   punctuation character off as its own token;
2. WordPiece: each word is split greedily into the longest vocabulary pieces from the left, pieces after
   the first prefixed with ``##``; a word that cannot be split (or is longer than 100 characters) becomes
   ``[UNK]``.

The caption for labels ``[a, b, c]`` is ``"a . b . c ."``, tokenized as ``[CLS] a . b . c . [SEP]``; each
label's token positions are kept so that detection scores per token map back to labels (`label_scores`).
`text_self_attention` builds GroundingDINO's block-diagonal text self-attention mask and position ids.
"""

from __future__ import annotations

import dataclasses
import logging
import unicodedata
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fmfusion_jax.errors import DataError

logger = logging.getLogger(__name__)

CLS, SEP, PAD, UNK = "[CLS]", "[SEP]", "[PAD]", "[UNK]"
#: Tokens that end a phrase in GroundingDINO's text attention ([CLS], [SEP], '.', '?').
PHRASE_BREAKS = (CLS, SEP, ".", "?")
MAX_CHARS_PER_WORD = 100


def _is_whitespace(char: str) -> bool:
    return char in " \t\n\r" or unicodedata.category(char) == "Zs"


def _is_control(char: str) -> bool:
    if char in "\t\n\r":
        return False
    return unicodedata.category(char).startswith("C")


def _is_punctuation(char: str) -> bool:
    code = ord(char)
    # All non-letter/number ASCII counts as punctuation (as in BERT), e.g. '$', '^', '`'.
    if 33 <= code <= 47 or 58 <= code <= 64 or 91 <= code <= 96 or 123 <= code <= 126:
        return True
    return unicodedata.category(char).startswith("P")


def _is_cjk(code: int) -> bool:
    return (
        0x4E00 <= code <= 0x9FFF
        or 0x3400 <= code <= 0x4DBF
        or 0x20000 <= code <= 0x2A6DF
        or 0x2A700 <= code <= 0x2B73F
        or 0x2B740 <= code <= 0x2B81F
        or 0x2B820 <= code <= 0x2CEAF
        or 0xF900 <= code <= 0xFAFF
        or 0x2F800 <= code <= 0x2FA1F
    )


def basic_tokenize(text: str) -> list[str]:
    """Cleans, lower-cases, strips accents and splits `text` on whitespace and punctuation."""
    cleaned = []
    for char in text:
        code = ord(char)
        if code == 0 or code == 0xFFFD or _is_control(char):
            continue
        if _is_whitespace(char):
            cleaned.append(" ")
        elif _is_cjk(code):
            cleaned.append(f" {char} ")
        else:
            cleaned.append(char)
    words = []
    for word in "".join(cleaned).split():
        word = unicodedata.normalize("NFD", word.lower())
        word = "".join(char for char in word if unicodedata.category(char) != "Mn")
        current = ""
        for char in word:
            if _is_punctuation(char):
                if current:
                    words.append(current)
                words.append(char)
                current = ""
            else:
                current += char
        if current:
            words.append(current)
    return words


class WordPieceTokenizer:
    """BERT's uncased tokenizer over a `vocab.txt` (one token per line, id = line number)."""

    def __init__(self, vocabulary: Sequence[str], source: str = "vocabulary"):
        self.tokens = list(vocabulary)
        self.ids: dict[str, int] = {}
        for index, token in enumerate(self.tokens):
            self.ids.setdefault(token, index)
        self.source = source
        missing = [token for token in (CLS, SEP, UNK, ".") if token not in self.ids]
        if missing:
            raise DataError(f"{source}: tokens {missing} missing; is this BERT's vocab.txt?")

    @classmethod
    def from_file(cls, path: str | Path) -> "WordPieceTokenizer":
        path = Path(path)
        try:
            lines = path.read_text(encoding="utf-8").split("\n")
        except (OSError, UnicodeDecodeError) as error:
            raise DataError(f"{path}: unreadable vocabulary ({error})") from None
        if lines and lines[-1] == "":
            lines.pop()
        return cls([line.rstrip("\r") for line in lines], source=str(path))

    def __len__(self) -> int:
        return len(self.tokens)

    def token_id(self, token: str) -> int:
        return self.ids.get(token, self.ids[UNK])

    def wordpiece(self, word: str) -> list[str]:
        """Greedy longest-match-first split of one basic token into vocabulary pieces (or ``[UNK]``)."""
        if len(word) > MAX_CHARS_PER_WORD:
            return [UNK]
        pieces, start = [], 0
        while start < len(word):
            end = len(word)
            piece = None
            while start < end:
                candidate = word[start:end] if start == 0 else "##" + word[start:end]
                if candidate in self.ids:
                    piece = candidate
                    break
                end -= 1
            if piece is None:
                return [UNK]
            pieces.append(piece)
            start = end
        return pieces

    def tokenize(self, text: str) -> list[str]:
        return [piece for word in basic_tokenize(text) for piece in self.wordpiece(word)]

    def encode(self, text: str) -> list[int]:
        """Ids of ``[CLS] text [SEP]``."""
        return [self.ids[CLS], *(self.token_id(t) for t in self.tokenize(text)), self.ids[SEP]]


@dataclasses.dataclass(frozen=True)
class Caption:
    """A GroundingDINO caption and where each label's tokens are.

    Attributes:
      text: ``"a . b ."``.
      labels: the labels encoded, in order (duplicates and labels beyond the token limit left out).
      tokens: ``[CLS] ... [SEP]``.
      input_ids: `(T,)` int64 ids of `tokens`.
      spans: per label, the `[start, end)` token positions of its words (without the '.').
      dropped: labels left out because the caption would exceed the token limit.
    """

    text: str
    labels: tuple[str, ...]
    tokens: tuple[str, ...]
    input_ids: np.ndarray
    spans: tuple[tuple[int, int], ...]
    dropped: tuple[str, ...] = ()

    @property
    def num_tokens(self) -> int:
        return len(self.tokens)


def build_caption(labels: Sequence[str], tokenizer: WordPieceTokenizer, max_tokens: int = 256) -> Caption:
    """Encodes ``labels`` as ``"a . b . c ."`` with each label's token span; at most `max_tokens` tokens.

    Labels are lower-cased (BERT is uncased) and deduplicated; a label whose tokens would not fit is left
    out entirely (listed in `dropped`, with a warning) rather than cut.
    """
    tokens, spans, kept, dropped = [CLS], [], [], []
    for label in labels:
        label = " ".join(label.lower().split())
        if not label or label in kept or label in dropped:
            continue
        pieces = tokenizer.tokenize(label)
        if not pieces:
            logger.warning("label %r has no token; left out of the caption", label)
            dropped.append(label)
            continue
        if len(tokens) + len(pieces) + 2 > max_tokens:  # its pieces, its '.', and the final [SEP]
            dropped.append(label)
            continue
        spans.append((len(tokens), len(tokens) + len(pieces)))
        tokens += [*pieces, "."]
        kept.append(label)
    tokens.append(SEP)
    if dropped:
        logger.warning("caption limited to %d tokens: labels %s left out", max_tokens, dropped)
    ids = np.array([tokenizer.token_id(t) for t in tokens], np.int64)
    text = " ".join(f"{label} ." for label in kept)
    return Caption(text, tuple(kept), tuple(tokens), ids, tuple(spans), tuple(dropped))


def text_self_attention(input_ids: np.ndarray, break_ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """GroundingDINO's text self-attention mask and position ids for one token sequence.

    The tokens between two phrase breaks, together with the closing break, form a phrase: its tokens attend
    to each other only, and their positions count 0, 1, ... from the phrase start. A break at the first or
    last position, and every token outside a phrase (padding), attends only to itself, at position 0.

    Returns `(T, T)` bool mask and `(T,)` int64 position ids.
    """
    ids = np.asarray(input_ids).reshape(-1)
    count = ids.shape[0]
    mask = np.eye(count, dtype=bool)
    positions = np.zeros(count, np.int64)
    previous: int | np.intp = 0
    for col in np.flatnonzero(np.isin(ids, np.asarray(list(break_ids)))):
        if 0 < col < count - 1:
            mask[previous + 1 : col + 1, previous + 1 : col + 1] = True
            positions[previous + 1 : col + 1] = np.arange(col - previous)
        previous = col
    return mask, positions


def label_scores(token_probs: np.ndarray, caption: Caption, text_threshold: float) -> list[dict[str, float]]:
    """Per query, label -> score: the max of the label's token probabilities, when every one of them passes.

    Args:
      token_probs: `(Q, >= T)` sigmoid scores per query and token position.
      caption: the caption the scores are for.
      text_threshold: a label counts only if all its tokens score strictly above this.
    """
    probs = np.asarray(token_probs, np.float32)
    result: list[dict[str, float]] = [{} for _ in range(probs.shape[0])]
    for label, (start, end) in zip(caption.labels, caption.spans):
        span = probs[:, start:end]
        passing = span.min(axis=1) > text_threshold
        best = span.max(axis=1)
        for query in np.flatnonzero(passing):
            result[query][label] = float(best[query])
    return result
