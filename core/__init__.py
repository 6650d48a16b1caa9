"""The ESGS engine. Importable without ``bpy`` (a test enforces it), and importing it changes
nothing in the process (no environment variables, no threads).

Layers, lowest first (docs/architecture.md; tests/core/test_layers.py enforces them):
foundation (errors, config, io_utils, progress, runtime) -> formats (formats, colmap,
datasets, terrain, metrics) -> render -> train -> priors (priors, ndn, labels) -> methods ->
applications (apps, experiments) -> cli (commands, cli).
"""
