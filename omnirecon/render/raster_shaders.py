"""GLSL programs of :class:`omnirecon.render.raster.MeshRasterizer`: the G-buffer, surface, depth and face-id passes.

Each pass writes float or int targets that are read back without conversion; ``1 / gl_FragCoord.w`` is the
camera z-depth because the projection puts camera z in ``w_clip`` (:func:`omnirecon.render.raster.projection_matrix`).
The G-buffer's vertex shader derives each corner's barycentric unit vector and the triangle id from ``gl_VertexID``
of an unindexed triangle list; the face pass reads ``gl_PrimitiveID`` of the indexed mesh.
"""

VERTEX_SHADER = """
#version 330 core
uniform mat4 world_to_clip;
in vec3 in_pos;
smooth out vec3 v_bary;
smooth out vec3 v_world;
flat out int v_face;
void main() {
    int k = gl_VertexID % 3;
    v_bary = vec3(k == 0, k == 1, k == 2);
    v_world = in_pos;
    v_face = gl_VertexID / 3;
    gl_Position = world_to_clip * vec4(in_pos, 1.0);
}
"""

SURFACE_VERTEX_SHADER = """
#version 330 core
uniform mat4 world_to_clip;
in vec3 in_pos;
smooth out vec3 v_world;
void main() {
    v_world = in_pos;
    gl_Position = world_to_clip * vec4(in_pos, 1.0);
}
"""

SURFACE_FRAGMENT_SHADER = """
#version 330 core
smooth in vec3 v_world;
layout(location = 0) out vec4 out_world_depth;
void main() {
    out_world_depth = vec4(v_world, 1.0 / gl_FragCoord.w);
}
"""

DEPTH_VERTEX_SHADER = """
#version 330 core
uniform mat4 world_to_clip;
in vec3 in_pos;
void main() {
    gl_Position = world_to_clip * vec4(in_pos, 1.0);
}
"""

DEPTH_FRAGMENT_SHADER = """
#version 330 core
layout(location = 0) out float out_depth;
void main() {
    out_depth = 1.0 / gl_FragCoord.w;
}
"""

FACE_FRAGMENT_SHADER = """
#version 330 core
layout(location = 0) out int out_face;
void main() {
    out_face = gl_PrimitiveID + 1;
}
"""

FRAGMENT_SHADER = """
#version 330 core
smooth in vec3 v_bary;
smooth in vec3 v_world;
flat in int v_face;
layout(location = 0) out int out_face;
layout(location = 1) out vec4 out_bary_depth;
layout(location = 2) out vec4 out_world;
void main() {
    out_face = v_face + 1;
    out_bary_depth = vec4(v_bary, 1.0 / gl_FragCoord.w);
    out_world = vec4(v_world, 1.0);
}
"""


PROGRAMS = {
    "gbuffer": (VERTEX_SHADER, FRAGMENT_SHADER),  # ids, barycentrics + z, world points
    "surface": (SURFACE_VERTEX_SHADER, SURFACE_FRAGMENT_SHADER),  # world point + z
    "depth": (DEPTH_VERTEX_SHADER, DEPTH_FRAGMENT_SHADER),  # z only
    "face": (DEPTH_VERTEX_SHADER, FACE_FRAGMENT_SHADER),  # triangle id + 1 only
}
"""(vertex shader, fragment shader) of each pass, by the name :class:`MeshRasterizer` draws it under."""
