"""A text encoder that answers phrases from a scene's ``text_embeddings.npz`` (docs/format.md).

Scenes whose mask features were not made by a real CLIP model (the synthetic room, tests) cannot be
queried with CLIP's text tower: their features live in another space. docs/format.md lets such a scene ship
``text_embeddings.npz``, phrase -> embedding in the space of its features, including the canonical
phrases of the relevancy score (``object``, ``things``, ``stuff``, ``texture``; LERF, LangSplat).
:class:`TableTextEncoder` serves that table through the :class:`~encoders.protocols.TextEncoder`
protocol and says plainly which phrase it does not know.

Example:
    >>> enc = TableTextEncoder("scene/text_embeddings.npz")  # doctest: +SKIP
    >>> enc.encode_text(["sofa", "object"]).shape  # doctest: +SKIP
    (2, 512)
"""

from __future__ import annotations

import difflib
import zipfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from encoders.protocols import CANONICAL_PHRASES, check_phrases

__all__ = ["CANONICAL_PHRASES", "TableTextEncoder", "TextTableError", "UnknownPhraseError"]

_LISTED = 20  # known phrases shown in an unknown-phrase message
_MIN_NORM = 1e-8  # a stored vector shorter than this has no direction


class TextTableError(ValueError):
    """A text_embeddings.npz that cannot be used; the message names the file and the key."""


class UnknownPhraseError(KeyError):
    """A phrase the table has no embedding for; the message names the phrase, the file, close matches.

    Attributes:
        phrase: the phrase asked for.
        path: the table's file.
        suggestions: known phrases close to it (difflib), best first; may be empty.
    """

    def __init__(self, phrase: str, path: Path, suggestions: list[str], known: list[str]) -> None:
        self.phrase, self.path, self.suggestions = phrase, path, suggestions
        hint = f" Did you mean {', '.join(repr(s) for s in suggestions)}?" if suggestions else ""
        shown = ", ".join(repr(k) for k in known[:_LISTED]) + (", ..." if len(known) > _LISTED else "")
        self.message = (
            f"{path}: no embedding for phrase {phrase!r}.{hint} Known phrases ({len(known)}): {shown}. "
            f"Add the phrase to the table, or query with a real text encoder."
        )
        super().__init__(self.message)

    def __str__(self) -> str:  # KeyError would show repr(message), quotes and escapes included
        return self.message


def _normalise_phrase(phrase: str) -> str:
    """Case and whitespace folded, as CLIP's tokenizer folds them (it lowercases and splits on spaces)."""
    return " ".join(phrase.lower().split())


class TableTextEncoder:
    """Phrases -> unit vectors looked up in a ``text_embeddings.npz`` (the text half of a CLIP encoder).

    A phrase matches its key exactly, or else after folding case and whitespace (CLIP's tokenizer
    folds both, so "Sofa " means "sofa"), provided the folded form names one key only. Stored vectors
    are L2-normalised at load.

    It implements :class:`~encoders.protocols.TextEncoder`; :meth:`encode_images` exists only to say
    clearly that a table cannot embed images.

    Args:
        path: the ``text_embeddings.npz`` file: keys are phrases, values finite 1-D vectors of one
            length with non-zero norm; the canonical phrases must be present.

    Raises:
        TextTableError: the file is missing or unreadable, or a key or value breaks the rules above
            (the message names the file and the key).

    Attributes:
        path: the table's file.
        dim: embedding dimension (the vectors' length).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        table = _load_table(self.path)
        self._phrases = sorted(table)
        self._index = {p: i for i, p in enumerate(self._phrases)}
        folded: dict[str, int | None] = {}
        for p, i in self._index.items():
            key = _normalise_phrase(p)
            folded[key] = None if key in folded else i  # None: two keys fold alike, so ask exactly
        self._folded = folded
        vectors = np.stack([table[p] for p in self._phrases]).astype(np.float64)
        self._vectors = (vectors / np.linalg.norm(vectors, axis=1, keepdims=True)).astype(np.float32)
        self.dim = int(self._vectors.shape[1])

    @property
    def phrases(self) -> list[str]:
        """Every phrase of the table, sorted."""
        return list(self._phrases)

    def __contains__(self, phrase: object) -> bool:
        return isinstance(phrase, str) and self._row(phrase) is not None

    def __len__(self) -> int:
        return len(self._phrases)

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        """Look phrases up.

        Args:
            phrases: P phrases (a list, not a bare string).

        Returns:
            [P, dim] float32 unit rows.

        Raises:
            UnknownPhraseError: for the first phrase the table does not hold.
        """
        phrases = check_phrases(phrases, "TableTextEncoder.encode_text")
        rows = []
        for phrase in phrases:
            row = self._row(phrase)
            if row is None:
                suggestions = difflib.get_close_matches(phrase, self._phrases, n=3, cutoff=0.6)
                raise UnknownPhraseError(phrase, self.path, suggestions, self._phrases)
            rows.append(row)
        return self._vectors[np.asarray(rows, dtype=np.int64)].reshape(len(rows), self.dim).copy()

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        """Always raises: a phrase table holds no image model."""
        raise NotImplementedError(
            f"TableTextEncoder ({self.path}) answers phrases only and cannot embed images; mask "
            f"features come from the scene's language_features/ cache or from a real ImageTextEncoder"
        )

    def _row(self, phrase: str) -> int | None:
        if phrase in self._index:
            return self._index[phrase]
        return self._folded.get(_normalise_phrase(phrase))

    def __repr__(self) -> str:
        return f"TableTextEncoder({str(self.path)!r}, {len(self)} phrases, dim={self.dim})"


def _load_table(path: Path) -> dict[str, np.ndarray]:
    """Every (phrase, vector) of the file, checked; TextTableError names the file and the key."""
    if not path.is_file():
        raise TextTableError(f"{path}: text embedding table not found")
    try:
        with np.load(path, allow_pickle=False) as npz:
            table = {key: np.asarray(npz[key]) for key in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise TextTableError(f"{path}: cannot read as an .npz of phrase -> vector ({err})") from err
    if not table:
        raise TextTableError(f"{path}: holds no phrases")
    for key in sorted(table):
        vec = table[key]
        if not key.strip():
            raise TextTableError(f"{path}: key {key!r} is an empty phrase")
        if vec.ndim != 1 or vec.shape[0] == 0:
            raise TextTableError(f"{path}: key {key!r} must be a non-empty 1-D vector, got shape {vec.shape}")
        if not (np.issubdtype(vec.dtype, np.floating) or np.issubdtype(vec.dtype, np.integer)):
            raise TextTableError(f"{path}: key {key!r} must hold numbers, got dtype {vec.dtype}")
        if not np.isfinite(vec).all():
            raise TextTableError(f"{path}: key {key!r} has NaN or inf values")
        if np.linalg.norm(vec.astype(np.float64)) < _MIN_NORM:
            raise TextTableError(f"{path}: key {key!r} is a zero vector (no direction to compare)")
    # The most common length is the table's; name a key that differs from it, not an arbitrary pair.
    lengths = Counter(v.shape[0] for v in table.values())
    dim = lengths.most_common(1)[0][0]
    odd = sorted(k for k, v in table.items() if v.shape[0] != dim)
    if odd:
        raise TextTableError(
            f"{path}: key {odd[0]!r} has length {table[odd[0]].shape[0]}, but most vectors have {dim} "
            f"({len(odd)} key(s) differ); all vectors must have one length"
        )
    missing = [p for p in CANONICAL_PHRASES if p not in table]
    if missing:
        raise TextTableError(
            f"{path}: missing the canonical phrase(s) {', '.join(repr(p) for p in missing)} that relevancy "
            f"compares every query against (docs/format.md, text_embeddings.npz)"
        )
    return table
