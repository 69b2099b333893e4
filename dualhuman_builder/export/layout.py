"""The dataset export (``dualhuman export``): its public names, gathered from the modules that hold them.

* :mod:`.files`: file names, the format version, byte-deterministic writers and safe readers;
* :mod:`.items`: :class:`ExportItem`, one sequence to export, and its validation;
* :mod:`.schema`: ``schema.json``, every array's shape, dtype, units and meaning;
* :mod:`.splits`: the seeded train/test split;
* :mod:`.writer`: :func:`export_dataset`, which writes the folder;
* :mod:`.card`: the dataset card (``README.md``), whose docstring documents the folder layout.
"""

from dualhuman_builder.export.card import dataset_card
from dualhuman_builder.export.files import (FORMAT, FORMAT_VERSION, LABELS_JSON, MANIFEST, OWN_FOLDERS, PERSONS,
                                            SEQ_ID_RE, SEQUENCE_JSON, check_seq_id, json_bytes, json_clean,
                                            load_contacts, load_motion, npy_bytes, npz_bytes, read_manifest,
                                            read_npz)  # fmt: skip
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.schema import build_schema
from dualhuman_builder.export.splits import make_splits
from dualhuman_builder.export.writer import STAGES, export_dataset

__all__ = ["FORMAT", "FORMAT_VERSION", "LABELS_JSON", "MANIFEST", "OWN_FOLDERS", "PERSONS", "SEQ_ID_RE",
           "SEQUENCE_JSON", "STAGES", "ExportItem", "build_schema", "check_seq_id", "dataset_card", "export_dataset",
           "json_bytes", "json_clean", "load_contacts", "load_motion", "make_splits", "npy_bytes", "npz_bytes",
           "read_manifest", "read_npz"]  # fmt: skip
