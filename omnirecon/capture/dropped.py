"""Why photos got no pose: one reason per unregistered photo, read from COLMAP's match graph.

:func:`match_graph` reads, per image, how many features were detected and the verified matches of
every image pair from a COLMAP database; :func:`drop_reasons` turns that and the models the mapper
produced into one short reason per photo left out, e.g. ``matched no other photo (412 features)``.
The reasons go into ``process.json`` (``dropped``) and the command's summary.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class MatchGraph:
    """Features per image and verified matches per image pair (names as in the database)."""

    features: dict[str, int] = field(default_factory=dict)
    """Keypoints detected in each image."""
    pairs: dict[tuple[str, str], int] = field(default_factory=dict)
    """Inlier matches of each geometrically verified pair ``(a, b)``, ``a < b``."""

    def neighbours(self, name: str, min_matches: int = 1) -> dict[str, int]:
        """The images ``name`` shares at least ``min_matches`` verified matches with, and how many."""
        out = {}
        for (a, b), k in self.pairs.items():
            if k >= min_matches and name in (a, b):
                out[b if a == name else a] = k
        return out

    def groups(self, min_matches: int = 15) -> list[list[str]]:
        """The connected groups of images (sorted names, largest group first) when two images are linked
        by a pair with at least ``min_matches`` verified matches: images of different groups share no
        usable match, so no mapping can pose them together."""
        link: dict[str, set[str]] = {n: set() for n in self.features}
        for (a, b), k in self.pairs.items():
            if k >= min_matches:
                link.setdefault(a, set()).add(b)
                link.setdefault(b, set()).add(a)
        seen: set[str] = set()
        out = []
        for start in sorted(link):
            if start in seen:
                continue
            group, todo = set(), [start]
            while todo:
                n = todo.pop()
                if n not in group:
                    group.add(n)
                    todo.extend(link[n] - group)
            seen |= group
            out.append(sorted(group))
        return sorted(out, key=lambda g: (-len(g), g))

    def reachable(self, names: list[str], min_matches: int = 15) -> list[str]:
        """Every image in a group (:meth:`groups`) with any of ``names``: the most a model holding
        ``names`` could pose with these features."""
        want = set(names)
        return sorted(n for g in self.groups(min_matches) if want & set(g) for n in g)


def match_graph(db_path: Path) -> MatchGraph:
    """Read :class:`MatchGraph` from the COLMAP database ``db_path``."""
    import pycolmap  # lazy: the optional 'capture' extra

    graph = MatchGraph()
    with pycolmap.Database.open(str(db_path)) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        for i, name in names.items():
            graph.features[name] = int(db.num_keypoints_for_image(i)) if hasattr(db, "num_keypoints_for_image") \
                else int(db.read_keypoints(i).shape[0])
        pair_ids, geometries = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pid) if isinstance(pid, int) else pid
            k = int(len(g.inlier_matches))
            if k and a in names and b in names:
                graph.pairs[tuple(sorted((names[a], names[b])))] = k
    return graph


def drop_reasons(names: list[str], registered: list[str], other_models: list[list[str]], graph: MatchGraph,
                 min_matches: int = 15) -> dict[str, str]:
    """One reason for each name in ``names`` that is not in ``registered`` (the kept model).

    ``other_models``: the images of each model that was not kept. ``min_matches``: the mapper's
    least number of verified matches for a pair to count. Reasons, in this order of precedence: no
    features; posed in a separate, smaller model (and whether that model's photos share any usable
    match with the kept ones); matched no other photo; in a group of photos that shares no usable
    match with the posed ones; matched only photos that got no pose either; matched posed photos but
    could not be posed from them.
    """
    kept = set(registered)
    in_other = {n: len(m) for m in other_models for n in m if n not in kept}
    linked = set(graph.reachable(registered, min_matches))
    group_of = {n: g for g in graph.groups(min_matches) for n in g}
    reasons = {}
    for name in names:
        if name in kept:
            continue
        feats = graph.features.get(name, 0)
        near = graph.neighbours(name, min_matches)
        posed = {n: k for n, k in near.items() if n in kept}
        if feats == 0:
            reasons[name] = "no features found (blank, blurred or fully masked photo)"
        elif name in in_other and name not in linked:
            reasons[name] = (f"posed in a separate model of {in_other[name]} photos that shares no pair of "
                             f"{min_matches}+ verified matches with the kept photos (add photos between the two sets "
                             "of views)")
        elif name in in_other:
            reasons[name] = (f"posed in a separate model of {in_other[name]} photos that shares too few matches "
                             "with the kept one")
        elif not near:
            weak = graph.neighbours(name, 1)
            most = max(weak.values(), default=0)
            reasons[name] = (f"matched no other photo ({feats} features; best pair {most} verified matches, "
                             f"{min_matches} needed)" if most else f"matched no other photo ({feats} features)")
        elif name not in linked:
            group = group_of.get(name, [name])
            shown = ", ".join(group[:6]) + (" ..." if len(group) > 6 else "")
            reasons[name] = (f"in a group of {len(group)} photos ({shown}) that shares no pair of {min_matches}+ "
                             "verified matches with the posed ones (add photos between these views and the rest)")
        elif not posed:
            reasons[name] = f"matched {len(near)} photos, none of which got a pose"
        else:
            reasons[name] = (f"matched {len(posed)} posed photos (at most {max(posed.values())} verified matches) "
                             "but too few of its features were triangulated to pose it")
    return reasons
