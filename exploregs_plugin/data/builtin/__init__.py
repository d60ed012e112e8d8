"""The built-in scenes: procedural worlds (``layouts``, ``textures``, a small ray tracer in
``raycast``) rendered into COLMAP (static, ``presets``) or Neu3D-style (dynamic, ``dynamic``)
datasets in the cache, as ``--data builtin:NAME`` reads them; ``blender_objects`` writes
Blender-layout object scenes (transforms.json)."""
