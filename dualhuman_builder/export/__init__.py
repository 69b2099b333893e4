"""Export stage: the training-ready dataset (``dualhuman export``).

Writing a folder export: ``items`` (the sequences to export and their validation), ``writer``
(:func:`~dualhuman_builder.export.writer.export_dataset`), ``files`` (file names, deterministic
writers, safe readers), ``schema`` (``schema.json``), ``splits`` (seeded train/test split),
``card`` (the dataset card, which documents the folder layout). Around it: ``collect`` (a
workspace's fitted takes -> export items), ``features`` (269-dim motion features and their inverse), ``interhuman`` (262-dim InterGen features), ``annotate``
(annotations in and out of a workspace), ``verify``, ``shards`` (WebDataset tars), ``loader``
(PyTorch datasets), ``convert`` (InterHuman and HumanML3D folder layouts).
"""
