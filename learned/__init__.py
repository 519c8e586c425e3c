"""The learned depth-pose network of EvtSlowTV (CVPRW 2025, sections 4.4-5).

Modules: :mod:`learned.model` (encoder-decoder with skips, multi-scale bounded inverse depth,
pose head), :mod:`learned.losses` (scale-invariant, gradient matching, teacher and student losses;
the contrast loss is :data:`cmax.contrast.SHARED_OBJECTIVE`, the objective of ``cmax.fit``'s shared polish), :mod:`learned.data`
(windows of h5 / MVSEC files, augmentations), :mod:`learned.config`, :mod:`learned.checkpoint`,
and the commands ``python -m learned.train``, ``python -m learned.evaluate``, ``python -m learned.predict``.
"""
