"""Batch processing of a dataset of sessions: the plan, a local process pool or Ray, retries.

``embodmocap batch DATASET`` (:func:`embodmocap.batch.run.run_batch`); the plan is
:func:`embodmocap.batch.plan.make_plan`. Nothing heavy is imported here: Ray (extra ``cluster``)
only when the Ray executor is chosen, the stages only inside the workers.
"""
