"""Generalizable renderers: ``encode(sources) -> SourceFeatures``, ``render_rays(features, rays) -> dict``."""
