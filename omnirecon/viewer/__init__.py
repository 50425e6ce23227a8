"""The static web viewer of baked meshes: export (:mod:`.export`, :mod:`.bundle`), serving (:mod:`.server`),
and a headless-Chromium driver for tests and frame-rate measurements (:mod:`.headless`).

The browser side lives in ``static/`` (``index.html``, ``viewer.js``, ``shaders.js``); three.js comes from npm
(``package.json`` here; ``npm install`` in this folder, run by ``make setup``) and is copied into each
exported bundle, so a bundle is self-contained and needs no CDN.
"""
