"""``sumoco map export NET --out map.glb``: the road network as glTF 2.0 binary."""

from __future__ import annotations

from typing import Any

from sumo_side.mapmesh import export_map


def cli_main(args: Any) -> int:
    mesh = export_map(args.net, args.out)
    print(f"{args.out}: {len(mesh.glb) / 1024:.1f} KiB, {mesh.vertices} vertices, {mesh.triangles} triangles, "
          f"{mesh.heads} signal heads, origin {mesh.origin[0]:.0f},{mesh.origin[1]:.0f} m, "
          f"{mesh.seconds:.2f} s, sha256 {mesh.sha256[:16]}")
    return 0
