"""Measuring a stylization: how far it moved toward the painting, what it kept, what it cost.

``metrics`` (pure functions: style distances, SSIM and gradient structure to the base render,
cross-view consistency by exact warps, render speed, the run log's time and memory), ``views``
(``evaluate_views``, the one novel-view evaluator of ``dresg evaluate``, the report and the quality bench),
``clip_dino`` (the paper's CLIP-S and DINO-C from local weights), ``report_measure`` (what the report
measures on the user's scene, paintings and cameras, as data), ``report`` (its Markdown and plots of error
against run time, drawn with matplotlib when it is installed), and ``stability`` (stiff and extreme inputs
through every stage). May import ``method``, ``raster``, ``scene`` and ``util``.
"""
