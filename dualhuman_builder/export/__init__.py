"""Export stage: the training-ready dataset. ``layout`` (folder layout, manifest, schema, splits),
``collect`` (a workspace's fitted takes -> export items), ``features`` (269-dim motion features and
their inverse), ``interhuman`` (262-dim InterGen features), ``labels`` / ``annotate`` (interaction
vocabulary, annotations in and out), ``verify``, ``shards`` (WebDataset tars), ``loader`` (PyTorch
datasets), ``convert`` (InterHuman and HumanML3D folder layouts)."""
