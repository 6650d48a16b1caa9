"""Applications built on the engine: the demo, its report, the training job the add-on starts
and the extension packaging."""
