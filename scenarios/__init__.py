"""The built-in scenarios, drive routes, street types and run presets.

This folder sits at the repository's top so that a reader finds the towns at
once; the wheel ships it as the package ``crchfl_sumo.scenarios`` (pyproject's
package-dir mapping), and the code reaches it only through
``crchfl_sumo.core.resources``.
"""
