"""The ESGS engine. Importable without ``bpy`` (a test enforces it).

Subpackages and modules each do one job; see docs/architecture.md.
"""
