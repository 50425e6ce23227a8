"""What kind of scene a capture is, decided once (:func:`scene_kind`), and the defaults that follow from it.

The mesh pipeline (depth source, visibility check, completion, hole filling), the mesh path (blend, fill, source
masks), the surface and how views are ranked all choose by the same few facts about a scene: its rig (an object
orbited or a forward-facing grid), whether object masks are used, whether its background colour is known
(procedural and Blender scenes) and whether the cameras walk along their view direction. :class:`SceneKind` holds
those facts and answers each choice by a property; nothing else compares a scene's ``rig``.
"""

from __future__ import annotations

from dataclasses import dataclass

from omnirecon.trajectory import is_walk


@dataclass(frozen=True)
class SceneKind:
    """The facts about a scene its defaults depend on (:func:`scene_kind`)."""

    rig: str = "unknown"
    """``"object"`` (cameras around an object), ``"forward"`` (a forward-facing grid, LLFF) or ``"unknown"``
    (:attr:`omnirecon.data.scene.Scene.rig`)."""
    masks: bool = False
    """Object masks are used: everything the scene photographs is inside them (free space carved outside, cleaning
    and completion within them)."""
    background: bool = False
    """The scene's background colour is known (composited renders: procedural and Blender scenes)."""
    walk: bool = False
    """The cameras walk along their view direction (:func:`omnirecon.trajectory.is_walk`: a street walked forward,
    or out and back, whatever the rig)."""

    @property
    def forward(self) -> bool:
        """A forward-facing capture: its content extends past the bounds behind it (a backdrop layer closes it)."""
        return self.rig == "forward"

    @property
    def object(self) -> bool:
        """An object capture: the cameras look at a centre (views ranked by angle about it, paths circle it)."""
        return self.rig == "object"

    def depth(self, has_model: bool = True) -> str:
        """The mesh's depth source (``omnirecon mesh --depth auto``, ``MeshOptions(depth="auto")``), by what ``python
        -m bench depth_sources`` measured (BENCHMARKS "Depth sources"): ``stereo`` (with completion) on forward-facing
        captures, with masks and without a model; elsewhere ``stereo+model`` (stereo where it matched, the model's
        coarse depth for the rest: stereo pairs only views within 60 degrees, and a sparse object capture leaves much
        of the depth uncovered)."""
        return "stereo" if not has_model or self.forward or self.masks else "stereo+model"

    @property
    def surface(self) -> str:
        """The mesh's surface (``omnirecon mesh --surface auto``): ``coherent`` on a walk (completion's fills, each
        from one photo's depth, are what its later photos and any other viewpoint see of the street), else
        ``fusion`` (with completion). BENCHMARKS "Away from the photos"."""
        return "coherent" if self.walk else "fusion"

    @property
    def occlusion(self) -> bool:
        """The visibility check before fusion (``MeshOptions.occlusion``) applies: not on forward-facing scenes,
        where it dropped the depth of thin structure in front of the background."""
        return not self.forward

    @property
    def object_without_masks(self) -> bool:
        """Not forward-facing and no masks: stereo's photometric refinement, the free-space check and the hole
        closing of the fused surface apply (``MeshOptions.refine``, ``free_space``, ``fill_holes``)."""
        return not self.forward and not self.masks

    @property
    def content_fill(self) -> bool:
        """Completion also covers the pixels that differ from the known background colour
        (``MeshOptions.content_fill``): object captures without masks."""
        return self.object_without_masks

    @property
    def confirmed_fill(self) -> bool:
        """Completion takes a view's own depth only where another map confirms it (``MeshOptions.confirmed_fill``):
        not on forward-facing captures, whose borders have no second view."""
        return not self.forward

    @property
    def real_object(self) -> bool:
        """An object capture of real photos (no known background colour)."""
        return self.object and not self.background

    @property
    def blend(self) -> str:
        """The mesh path's blend (``finetune --blend auto``, the real-time renders): ``angle`` on real object
        captures (with masks or without), else the network's (BENCHMARKS "Depth sources")."""
        return "angle" if self.real_object else "network"

    @property
    def fill(self) -> str:
        """The mesh path's fill where no surface is (``finetune --fill auto``): the known ``background`` colour, the
        ``nearest`` surface on real object captures, else the ``far`` layer (forward-facing scenes)."""
        return "background" if self.background else ("nearest" if self.real_object else "far")

    @property
    def source_masks(self) -> bool:
        """The masks hold everything the scene photographs (a real object capture with masks, DTU), so a source pixel
        off its mask shows background, never surface (the angle blend's source masks)."""
        return self.real_object and self.masks

    @property
    def rank_by(self) -> str:
        """How views are ranked as each other's neighbours: by ``angle`` about the look-at centre on object
        captures, else by camera ``distance``."""
        return "angle" if self.object else "distance"


def scene_kind(scene, masks: bool | None = None) -> SceneKind:
    """The :class:`SceneKind` of ``scene`` (a :class:`~omnirecon.data.scene.Scene`, or anything with its ``rig``,
    ``masks``, ``background`` and ``cameras``; missing ones count as unknown / absent). ``masks``: whether its
    object masks are used (``None``: whether it has them; ``True`` counts only when it has them)."""
    has = getattr(scene, "masks", None) is not None
    cams = getattr(scene, "cameras", None)
    return SceneKind(rig=getattr(scene, "rig", "unknown") or "unknown", masks=has if masks is None else has and masks,
                     background=getattr(scene, "background", None) is not None,
                     walk=cams is not None and is_walk(cams))
