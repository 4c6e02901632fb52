"""Stage II, sequence processing: sync the two views, slice them to a common timeline, and gather
per-frame human observations (see ``embodmocap sequence``).

Modules: :mod:`~embodmocap.sequence.sync` (laser-dot sync and contact sheets),
:mod:`~embodmocap.sequence.slicing` (common timeline and frame maps),
:mod:`~embodmocap.sequence.sync_record` (``sync.json``: every source and the choice),
:mod:`~embodmocap.sequence.geosync` (geometric sync, run by Stage III after registration),
:mod:`~embodmocap.sequence.subframe` (view 2 resampled at view 1's instants, for Stage IV). Import from the modules; this
package imports nothing so that ``import embodmocap.sequence.x`` stays cheap.
"""
