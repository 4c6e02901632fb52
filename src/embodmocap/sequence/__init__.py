"""Stage II, sequence processing: sync the two views, slice them to a common timeline, and gather
per-frame human observations (see ``embodmocap sequence``).

Modules: :mod:`~embodmocap.sequence.sync` (laser-dot sync and contact sheets),
:mod:`~embodmocap.sequence.slicing` (common timeline and frame maps). Import from the modules; this
package imports nothing so that ``import embodmocap.sequence.x`` stays cheap.
"""
