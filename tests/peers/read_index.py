"""Reads a labrig dataset index (a directory of Parquet parts) with pyarrow, independently of
labrig, and runs a retrieval query on it.

usage: read_index.py INDEX_DIR QUERY_JSON
QUERY_JSON: {"object": "cube", "cam": [x, y, z], "cam_xy": 0.2, "cam_z": 0.1,
             "box_centre": [x, y, z], "box": [0.6, 0.6, 0.3]}
prints one JSON object: the columns, the rows (id, object position, ext1 x, bin and pose source),
and the ids the query keeps (object, then some external camera near the target camera, then the
object box).
"""
import glob
import json
import os
import sys

import pyarrow.compute as pc
import pyarrow.parquet as pq

index, query = sys.argv[1], json.loads(sys.argv[2])
table = pq.ParquetDataset(sorted(glob.glob(os.path.join(index, "part-*.parquet")))).read()
cols = table.column_names
kept = table.filter(pc.equal(table["object"], query["object"]))
cx, cy, cz = query["cam"]
near = None
for cam in ["ext1", "ext2", "rs1", "rs2"]:
    m = pc.and_(
        pc.and_(
            pc.less_equal(pc.abs(pc.subtract(kept[f"{cam}_x"], cx)), query["cam_xy"]),
            pc.less_equal(pc.abs(pc.subtract(kept[f"{cam}_y"], cy)), query["cam_xy"]),
        ),
        pc.less_equal(pc.abs(pc.subtract(kept[f"{cam}_z"], cz)), query["cam_z"]),
    )
    m = pc.fill_null(m, False)
    near = m if near is None else pc.or_(near, m)
kept = kept.filter(near)
bx, by, bz = query["box_centre"]
hx, hy, hz = [v / 2 for v in query["box"]]
inside = pc.and_(
    pc.and_(
        pc.less_equal(pc.abs(pc.subtract(kept["object_x"], bx)), hx),
        pc.less_equal(pc.abs(pc.subtract(kept["object_y"], by)), hy),
    ),
    pc.less_equal(pc.abs(pc.subtract(kept["object_z"], bz)), hz),
)
kept = kept.filter(pc.fill_null(inside, False))
rows = table.select(
    ["episode_id", "object_x", "object_y", "object_z", "ext1_x", "ext1_bin", "ext1_extrinsics_from", "source_format"]
).to_pylist()
print(json.dumps({"columns": cols, "rows": rows, "kept": sorted(kept["episode_id"].to_pylist())}))
