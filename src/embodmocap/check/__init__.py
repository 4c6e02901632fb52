"""`embodmocap check`: the on-the-spot verdict on a capture (:mod:`embodmocap.check.core`)."""
