"""OpenCLIP image and text towers run with onnxruntime: the real :class:`ImageTextEncoder` of eq. 1.

A model folder is written by ``langfield export clip`` (:func:`encoders.export.clip.export_clip`)::

    clip/
      manifest.json                   kind "clip": input_size, mean, std, context_length, dim
      image.onnx                      pixels [B, 3, S, S] (CLIP-normalised) -> [B, dim] unit rows
      text.onnx                       tokens [B, context_length] int64 -> [B, dim] unit rows
      bpe_simple_vocab_16e6.txt.gz    open_clip's BPE merges, copied from the installed package

Tokenizer. :class:`ClipTokenizer` reproduces ``open_clip.tokenize`` (open_clip ``tokenizer.py``,
``SimpleTokenizer``, itself OpenAI CLIP's): text cleaning (``ftfy.fix_text``, HTML unescaping twice,
whitespace collapsing, lower case), the pre-tokenising regex
``<start_of_text>|<end_of_text>|'s|'t|'re|'ve|'m|'ll|'d|[\\p{L}]+|[\\p{N}]|[^\\s\\p{L}\\p{N}]+``
(case-insensitive), GPT-2's byte-to-unicode table, byte-pair merges with a ``</w>`` end-of-word
suffix over the first 48894 merges of the vocabulary file, then ``[SOT] + tokens + [EOT]`` padded with
0 to the context length, or cut to it with EOT as the last token. The regex (Unicode letter and
number classes, which Python's ``re`` lacks) and the merge loop run in the Hugging Face ``tokenizers``
library (``pre_tokenizers.Split`` and ``models.BPE``): a well-kept, offline, compiled library, so
langfield carries no BPE implementation of its own; the vocabulary is open_clip's own file, shipped
beside the model, so there is no conversion step that could drift. Tokens equal those of
``open_clip.tokenize`` (tests compare them on phrases with punctuation, case, digits, accents).

``ftfy`` (which repairs mojibake, curly quotes, ligatures, full-width forms) is used when it is
installed, as open_clip does. Without it, phrases made only of printable ASCII other than ``&`` (plus
tab, newline, carriage return, form feed) are tokenized exactly, since ``ftfy.fix_text`` leaves those
unchanged; any other phrase raises an error asking for ``pip install ftfy`` rather than risking
different tokens.

Example:
    >>> enc = OnnxClipEncoder("models/clip")  # doctest: +SKIP
    >>> enc.encode_text(["a red sofa"]).shape, enc.image_size  # doctest: +SKIP
    ((1, 512), 224)
"""

from __future__ import annotations

import gzip
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from encoders.manifest import ManifestError, manifest_normalisation, onnx_session, read_manifest
from encoders.protocols import check_crops, check_phrases

__all__ = ["ClipTokenizer", "OnnxClipEncoder", "bytes_to_unicode", "clean_text"]

# open_clip SimpleTokenizer: merges = lines[1 : 49152 - 256 - 2 + 1] (line 0 is a version header).
_NUM_MERGES = 49152 - 256 - 2
_SPECIAL = ("<start_of_text>", "<end_of_text>")
_PATTERN = r"(?i)<start_of_text>|<end_of_text>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"
# Characters ftfy.fix_text leaves as they are ('&' may start an HTML entity ftfy unescapes once more,
# vertical tab and other control characters are removed by it).
_FTFY_INVARIANT = frozenset(map(chr, range(0x20, 0x7F))) - {"&"} | {"\t", "\n", "\r", "\x0c"}


def bytes_to_unicode() -> dict[int, str]:
    """GPT-2 / CLIP byte -> printable character table: printable Latin-1 bytes map to themselves."""
    ranges = (range(ord("!"), ord("~") + 1), range(ord("¡"), ord("¬") + 1), range(ord("®"), ord("ÿ") + 1))
    table = {b: chr(b) for r in ranges for b in r}
    extra = 0
    for b in range(256):
        if b not in table:
            table[b] = chr(256 + extra)
            extra += 1
    return table


class ClipTokenizer:
    """``open_clip.tokenize`` from open_clip's BPE vocabulary file, on the ``tokenizers`` library.

    Args:
        vocab_path: ``bpe_simple_vocab_16e6.txt.gz`` (gzip, a header line then one merge per line).
        context_length: tokens per phrase (77 for CLIP).

    Example:
        >>> tok = ClipTokenizer("models/clip/bpe_simple_vocab_16e6.txt.gz")  # doctest: +SKIP
        >>> tok(["a cat"])[0, :4].tolist()  # doctest: +SKIP
        [49406, 320, 2368, 49407]
    """

    def __init__(self, vocab_path: str | Path, context_length: int = 77) -> None:
        try:
            from tokenizers import Regex, models, pre_tokenizers
        except ImportError as exc:  # a main dependency; only a broken install lacks it
            raise ImportError("ClipTokenizer needs the 'tokenizers' package: pip install tokenizers") from exc
        if context_length < 2:
            raise ValueError(f"ClipTokenizer: context_length must be >= 2, got {context_length}")
        self.vocab_path = Path(vocab_path)
        self.context_length = int(context_length)
        merges = _read_merges(self.vocab_path)
        byte_chars = list(bytes_to_unicode().values())
        tokens = byte_chars + [c + "</w>" for c in byte_chars] + ["".join(m) for m in merges] + list(_SPECIAL)
        self.vocab_size = len(tokens)
        self.sot_id, self.eot_id = self.vocab_size - 2, self.vocab_size - 1
        self._byte_encoder = bytes_to_unicode()
        self._bpe = models.BPE(
            vocab={t: i for i, t in enumerate(tokens)}, merges=merges, end_of_word_suffix="</w>"
        )
        self._split = pre_tokenizers.Split(Regex(_PATTERN), behavior="removed", invert=True)
        self._special_ids = dict(zip(_SPECIAL, (self.sot_id, self.eot_id), strict=True))

    def encode(self, text: str) -> list[int]:
        """BPE ids of one phrase, without SOT / EOT (open_clip ``SimpleTokenizer.encode``)."""
        ids: list[int] = []
        for piece, _ in self._split.pre_tokenize_str(clean_text(text)):
            if piece in self._special_ids:  # open_clip's BPE cache maps a typed special token to itself
                ids.append(self._special_ids[piece])
                continue
            chars = "".join(self._byte_encoder[b] for b in piece.encode("utf-8"))
            ids.extend(token.id for token in self._bpe.tokenize(chars))
        return ids

    def __call__(self, phrases: Sequence[str]) -> np.ndarray:
        """Tokens of phrases as ``open_clip.tokenize`` gives them.

        Args:
            phrases: P phrases.

        Returns:
            [P, context_length] int64: SOT, the BPE ids, EOT, then zeros; a phrase too long is cut to
            the context length and its last token set to EOT.
        """
        phrases = check_phrases(phrases, "ClipTokenizer", allow_empty=True)
        out = np.zeros((len(phrases), self.context_length), dtype=np.int64)
        for i, phrase in enumerate(phrases):
            ids = [self.sot_id, *self.encode(phrase), self.eot_id][: self.context_length]
            ids[-1] = self.eot_id
            out[i, : len(ids)] = ids
        return out


def clean_text(text: str) -> str:
    """open_clip's ``_clean_lower``: ftfy, HTML unescaping twice, whitespace collapsed, lower case."""
    try:
        import ftfy
    except ImportError:
        if not set(text) <= _FTFY_INVARIANT:
            raise ValueError(
                f"phrase {text!r} has characters that open_clip cleans with ftfy.fix_text (non-ASCII, '&' "
                f"or control characters), and ftfy is not installed: pip install ftfy"
            ) from None
    else:
        text = ftfy.fix_text(text)
    text = html.unescape(html.unescape(text)).strip()
    return " ".join(text.split()).lower()


def _read_merges(path: Path) -> list[tuple[str, str]]:
    """The BPE merges open_clip uses: lines 1 .. 48894 of the gzip file, two symbols each."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: CLIP BPE vocabulary file not found")
    try:
        lines = gzip.decompress(path.read_bytes()).decode("utf-8").split("\n")
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a gzip-compressed UTF-8 BPE vocabulary ({exc})") from exc
    body = lines[1 : 1 + _NUM_MERGES]
    if body and body[-1] == "":  # a short file's final newline
        body = body[:-1]
    merges = []
    for number, line in enumerate(body, start=2):
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"{path}: line {number} is not a merge of two symbols: {line!r}")
        merges.append((parts[0], parts[1]))
    if not merges:
        raise ValueError(f"{path}: holds no BPE merges")
    return merges


class OnnxClipEncoder:
    """OpenCLIP exported to ONNX (``langfield export clip``), behind the ImageTextEncoder protocol.

    Images are normalised with the manifest's mean and std (CLIP's), transposed to NCHW and embedded
    by ``image.onnx``; phrases are tokenized by :class:`ClipTokenizer` and embedded by ``text.onnx``.
    Both towers end with L2 normalisation (eq. 1).

    Args:
        model_dir: the folder ``langfield export clip --out`` wrote.

    Attributes:
        dim: embedding dimension (512 for ViT-B-16).
        image_size: side S of the square crops :meth:`encode_images` takes (224 for ViT-B-16).
        model: the manifest's model name (architecture / weights).

    Raises:
        ManifestError: a missing or malformed manifest, or a model file missing; the message names it.
        ValueError: an ONNX file whose inputs or outputs disagree with the manifest.

    Example:
        >>> enc = OnnxClipEncoder("models/clip")  # doctest: +SKIP
        >>> enc.encode_images(np.zeros((2, 224, 224, 3), np.float32)).shape  # doctest: +SKIP
        (2, 512)
    """

    def __init__(self, model_dir: str | Path) -> None:
        self.model_dir = Path(model_dir)
        manifest = read_manifest(self.model_dir, "clip")
        where = self.model_dir / "manifest.json"
        for role in ("image", "text", "vocab"):
            if role not in manifest["files"]:
                raise ManifestError(f"{where}: 'files' has no {role!r} entry")
        self.model = str(manifest.get("model", ""))
        self.image_size = _positive_int(manifest, "input_size", where)
        self.dim = _positive_int(manifest, "dim", where)
        self.context_length = _positive_int(manifest, "context_length", where)
        self._mean, self._std = manifest_normalisation(manifest, where)
        if manifest.get("output") != "unit":
            raise ManifestError(
                f"{where}: 'output' must be 'unit' (L2-normalised rows), got {manifest.get('output')!r}"
            )
        self.tokenizer = ClipTokenizer(manifest["files"]["vocab"], self.context_length)
        if manifest.get("vocab_size") != self.tokenizer.vocab_size:
            raise ManifestError(
                f"{where}: 'vocab_size' is {manifest.get('vocab_size')!r} but {manifest['files']['vocab']} "
                f"gives {self.tokenizer.vocab_size} tokens"
            )
        self._image_path, self._text_path = manifest["files"]["image"], manifest["files"]["text"]
        self._image = onnx_session(self._image_path)
        self._text = onnx_session(self._text_path)
        _check_io(self._image, self._image_path, [3, self.image_size, self.image_size], self.dim)
        _check_io(self._text, self._text_path, [self.context_length], self.dim)

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        """Embed square crops.

        Args:
            images: [B, S, S, 3] float RGB in [0, 1], S = image_size.

        Returns:
            [B, dim] float32 unit rows.
        """
        arr = check_crops(images, self.image_size, "OnnxClipEncoder.encode_images")
        if arr.shape[0] == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        pixels = ((arr.astype(np.float32) - self._mean) / self._std).transpose(0, 3, 1, 2)
        return self._run(self._image, np.ascontiguousarray(pixels), self._image_path)

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        """Embed phrases.

        Args:
            phrases: P phrases.

        Returns:
            [P, dim] float32 unit rows.
        """
        phrases = check_phrases(phrases, "OnnxClipEncoder.encode_text")
        tokens = self.tokenizer(phrases)
        if tokens.shape[0] == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return self._run(self._text, tokens, self._text_path)

    def _run(self, session: Any, x: np.ndarray, path: Path) -> np.ndarray:
        out = np.asarray(session.run(None, {session.get_inputs()[0].name: x})[0], dtype=np.float64)
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        if out.shape != (x.shape[0], self.dim) or not np.isfinite(norms).all() or (norms == 0).any():
            raise ValueError(
                f"{path}: returned shape {out.shape}, or NaN, inf or zero rows "
                f"(expected [{x.shape[0]}, {self.dim}] unit rows)"
            )
        return (out / norms).astype(np.float32)  # already unit; this only removes float32 rounding


def _check_io(session: Any, path: Path, feature_shape: list[int], dim: int) -> None:
    """One input [batch, *feature_shape] and a first output [batch, dim], as the manifest says."""
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1:
        raise ValueError(f"{path}: expected one input, got {[i.name for i in inputs]}")
    shape = list(inputs[0].shape)
    if len(shape) != 1 + len(feature_shape) or shape[1:] != feature_shape:
        expected = ", ".join(map(str, ["batch", *feature_shape]))
        raise ValueError(f"{path}: input {inputs[0].name!r} has shape {shape}, expected [{expected}]")
    out = list(outputs[0].shape)
    if len(out) != 2 or out[1] != dim:
        raise ValueError(f"{path}: output {outputs[0].name!r} has shape {out}, expected [batch, {dim}]")


def _positive_int(manifest: dict, key: str, where: Path) -> int:
    value = manifest.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ManifestError(f"{where}: {key!r} must be a positive integer, got {value!r}")
    return value
