"""Export stage: the training-ready dataset (folder layout with manifest and schema, 269-dim motion
features, contacts, text and labels, splits, WebDataset shards, loaders, converters to
InterHuman and HumanML3D layouts). Arrives with the export issue."""
