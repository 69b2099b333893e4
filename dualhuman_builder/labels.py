"""Interaction labels: the vocabulary, and the annotation record a sequence carries.

The vocabulary (``dualhuman_builder/vocabulary.toml``, extended per project by ``WS/labels.toml``) is an
ordered list of label names, each with a description, a ``one_sided`` flag (one person acts, the
other reacts) and where it comes from (CHI3D's eight types, NTU RGB+D 120's mutual actions, this
toolkit's scene types). Its order is the order of the exported multi-hot vector.

An :class:`Annotation` is one annotator's account of a take (``sequence`` None) or of one of its
sequences: labels from the vocabulary, free-text descriptions, the actor and reactor (actor names
of the take) for one-sided interactions, the symmetric flag, the annotator and when. The catalog
keeps one per (take, sequence, annotator); :mod:`dualhuman_builder.export.annotate` reads and
writes them as CSV or JSON Lines.
"""

from __future__ import annotations

import difflib
import re
import tomllib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from dualhuman_builder.resources import VOCABULARY_PATH

BUILTIN_VOCABULARY = VOCABULARY_PATH
#: File name of a workspace's own additions to the vocabulary.
PROJECT_VOCABULARY = "labels.toml"
_NAME = re.compile(r"^[a-z][a-z0-9_]{0,63}$")


@dataclass(frozen=True)
class Label:
    """One vocabulary entry. ``name``: lower_snake_case, at most 64 characters."""

    name: str
    description: str
    one_sided: bool
    sources: tuple[str, ...] = ()


@dataclass(frozen=True)
class Vocabulary:
    """An ordered set of :class:`Label`; index ``i`` is position ``i`` of the multi-hot vector."""

    labels: tuple[Label, ...]
    origins: tuple[str, ...] = ()  # the files it was read from
    _index: dict[str, int] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        self._index.update({lab.name: i for i, lab in enumerate(self.labels)})

    @property
    def names(self) -> list[str]:
        return [lab.name for lab in self.labels]

    def __len__(self) -> int:
        return len(self.labels)

    def __contains__(self, name: object) -> bool:
        return name in self._index

    def __getitem__(self, name: str) -> Label:
        return self.labels[self.index(name)]

    def index(self, name: str) -> int:
        """Position of ``name``; ValueError naming the closest known labels otherwise."""
        try:
            return self._index[name]
        except KeyError:
            raise ValueError(self.unknown_message(name)) from None

    def unknown_message(self, name: str) -> str:
        close = difflib.get_close_matches(str(name), self.names, n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        return (f"label {name!r} is not in the interaction vocabulary ({len(self)} labels: "
                f"{', '.join(self.names[:8])}, ...){hint} Add project labels to WS/{PROJECT_VOCABULARY}")  # fmt: skip

    def check(self, labels: Iterable[str]) -> list[str]:
        """``labels`` as a list without repeats, in their given order; ValueError for an unknown one."""
        out: list[str] = []
        for name in labels:
            self.index(name)
            if name not in out:
                out.append(name)
        return out

    def multi_hot(self, labels: Iterable[str]) -> np.ndarray:
        """``(K,)`` uint8: 1 at each label's index, K = ``len(self)``."""
        v = np.zeros(len(self), np.uint8)
        for name in labels:
            v[self.index(name)] = 1
        return v

    def symmetric(self, labels: Iterable[str]) -> bool | None:
        """True when no label is one-sided, False when one is, None for no labels."""
        labels = list(labels)
        return None if not labels else not any(self[n].one_sided for n in labels)

    def as_dict(self) -> dict:
        """``labels.json`` of an export: the entries in multi-hot order, with their index."""
        return {"version": 1, "size": len(self), "labels": [
            {"index": i, "name": lab.name, "description": lab.description, "one_sided": lab.one_sided,
             "sources": list(lab.sources)} for i, lab in enumerate(self.labels)]}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Mapping) -> Vocabulary:
        """Inverse of :meth:`as_dict` (entries must be in index order)."""
        labels = d.get("labels") if isinstance(d, Mapping) else None
        if not isinstance(labels, list):
            raise ValueError("a vocabulary needs a list 'labels'")
        for i, e in enumerate(labels):
            if not isinstance(e, Mapping) or e.get("index", i) != i:
                raise ValueError(f"vocabulary entry {i} is not an object with index {i}")
        return cls(tuple(_label(e, f"entry {i}") for i, e in enumerate(labels)))


def _label(e, where: str) -> Label:
    if not isinstance(e, Mapping):
        raise ValueError(f"{where}: a label must be a table with name, description, one_sided")
    name, desc, one_sided = e.get("name"), e.get("description", ""), e.get("one_sided")
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{where}: label name {name!r} must be lower_snake_case (a-z, 0-9, _), at most 64 characters")
    if not isinstance(desc, str):
        raise ValueError(f"{where}: label {name!r}: description must be text")
    if not isinstance(one_sided, bool):
        raise ValueError(f"{where}: label {name!r}: one_sided must be true or false, got {one_sided!r}")
    sources = e.get("sources", [])
    if not isinstance(sources, list) or not all(isinstance(s, str) for s in sources):
        raise ValueError(f"{where}: label {name!r}: sources must be a list of strings")
    return Label(name, desc, one_sided, tuple(sources))


def read_vocabulary_file(path: str | Path) -> list[Label]:
    """The ``[[label]]`` entries of a vocabulary TOML file; ValueError naming the file and entry."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"{path}: not a valid UTF-8 TOML file ({e})") from None
    entries = doc.get("label", [])
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: no [[label]] entries")
    return [_label(e, f"{path} label {i + 1}") for i, e in enumerate(entries)]


def load_vocabulary(workspace_root: str | Path | None = None) -> Vocabulary:
    """The built-in vocabulary, extended by ``WS/labels.toml`` when ``workspace_root`` has one
    (its labels are appended in file order; redefining a built-in name is an error)."""
    labels = read_vocabulary_file(BUILTIN_VOCABULARY)
    origins = [str(BUILTIN_VOCABULARY)]
    extra = Path(workspace_root) / PROJECT_VOCABULARY if workspace_root is not None else None
    if extra is not None and extra.is_file():
        known = {lab.name for lab in labels}
        for lab in read_vocabulary_file(extra):
            if lab.name in known:
                raise ValueError(f"{extra}: label {lab.name!r} is already in the vocabulary; choose another name")
            known.add(lab.name)
            labels.append(lab)
        origins.append(str(extra))
    dupes = sorted(n for n, c in Counter(lab.name for lab in labels).items() if c > 1)
    if dupes:
        raise ValueError(f"vocabulary defines {dupes} more than once")
    return Vocabulary(tuple(labels), tuple(origins))


@dataclass(frozen=True)
class Annotation:
    """One annotator's labels for a take (``sequence`` None) or one of its sequences.

    ``labels``: vocabulary names; ``texts``: free-text descriptions (UTF-8 str); ``actor`` /
    ``reactor``: actor names of the take for a one-sided interaction (None: symmetric or not
    annotated); ``symmetric``: the interaction has no actor/reactor (None: not said);
    ``annotated_at``: ISO 8601 time; ``source``: the file it was imported from, if any.
    """

    take: str
    sequence: str | None
    annotator: str
    labels: tuple[str, ...] = ()
    texts: tuple[str, ...] = ()
    actor: str | None = None
    reactor: str | None = None
    symmetric: bool | None = None
    annotated_at: str = ""
    source: str | None = None

    def as_dict(self) -> dict:
        return {"take": self.take, "sequence": self.sequence, "labels": list(self.labels), "texts": list(self.texts),
                "actor": self.actor, "reactor": self.reactor, "symmetric": self.symmetric,
                "annotator": self.annotator, "annotated_at": self.annotated_at}  # fmt: skip


def check_annotation(a: Annotation, vocabulary: Vocabulary, take_actors: Iterable[str]) -> Annotation:
    """``a`` with its labels de-duplicated, its reactor filled in from the take's two actors and
    its symmetric flag derived from the labels when not given; ValueError for an unknown label,
    roles that are not the take's actors, roles on a symmetric interaction, or empty text."""
    labels = tuple(vocabulary.check(a.labels))
    texts = tuple(t.strip() for t in a.texts)
    if any(not t for t in texts):
        raise ValueError("a text description is empty")
    actors = list(take_actors)
    actor, reactor = a.actor or None, a.reactor or None
    for role, name in (("actor", actor), ("reactor", reactor)):
        if name is not None and name not in actors:
            raise ValueError(f"{role} {name!r} is not in this take (its actors: {actors})")
    if actor is not None and actor == reactor:
        raise ValueError(f"actor and reactor are both {actor!r}")
    if len(actors) == 2 and (actor is None) != (reactor is None):
        known = actor or reactor
        other = actors[1 - actors.index(known)]
        actor, reactor = (actor, other) if actor else (other, reactor)
    symmetric = a.symmetric
    if symmetric is None and actor is None:
        symmetric = vocabulary.symmetric(labels)
    elif symmetric is None:
        symmetric = False
    if symmetric and actor is not None:
        raise ValueError("a symmetric interaction has no actor and reactor; leave them empty or set symmetric false")
    return Annotation(a.take, a.sequence, a.annotator, labels, texts, actor, reactor, symmetric, a.annotated_at, a.source)
