"""The ground floor: the one user-error type, TOML configs read into frozen
dataclasses, atomic writes, execution backends (in-process, spawned
processes, Ray), paths to the packaged scenarios, and figure helpers.

May import: nothing else of the package.
"""
