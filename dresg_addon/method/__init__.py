"""The paper's method (DReSG, Secs. 4.1-4.3 and Algorithm 1), one module per section.

``config`` (the typed settings and presets), ``views`` (active views by capped coverage, Eqs. 13-15),
``schedule`` (stages, DDIM timesteps and the residual strength gamma_n), ``proposal`` (the
attention-guided proposal backends: ``synth``, weight-free, and ``sd15``), ``backends`` (their registry),
``targets`` (render-relative residual targets, Eqs. 10-12), ``losses`` (the fit loss, Eq. 16), ``pcgrad``
(colour-gradient fusion, Eqs. 17-20), ``optim`` (Adam groups and geometry bounds), ``fitting`` (multi-view
fitting of the seen Gaussians), ``color_transfer`` (the post stage's covariance colour transfer),
``style_distance`` (the sliced Wasserstein distance the early stop uses), ``dino`` (the optional DINO
feature term), and ``loop`` (Algorithm 1 as a short loop of these steps, with ``bookkeeping`` for
progress, cancel, checkpoints and the log). May import ``raster``, ``scene`` and ``util``.
"""
