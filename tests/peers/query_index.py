"""Reads labrig dataset indexes with pyarrow and DuckDB, independently of labrig (issue 36).

An index is either flat (a folder of `part-IIIII-of-NNNNN.parquet`, what `labrig dataset index
--shard` writes) or merged (`labrig dataset merge`: hive-partitioned,
`source_format=<fmt>/part-*.parquet`, the key in the folder name only); both are read with
hive partitioning on where there are partitions, the way a user would: `pq.read_table(dir)`,
`ds.dataset(dir, partitioning="hive")`, DuckDB's `read_parquet(..., hive_partitioning = true)`.

usage:
  query_index.py compare INDEX_A INDEX_B
      every column of every row, sorted by source_path: {"equal", "rows_a", "rows_b",
      "columns_a", "columns_b", "differences": [...first few...], "partitions_consistent"}
  query_index.py query INDEX QUERY_JSON
      QUERY_JSON: {"cameras": [[x, y, z], ...], "cam_xy": 0.2, "cam_z": 0.1,
                   "box_centre": [x, y, z], "box": [0.6, 0.6, 0.3]}
      camPose (every target camera has some external camera of the row (ext1, ext2, rs1, rs2)
      within cam_xy in x and y and cam_z in z) then objSpat (the object position in the box
      centred on box_centre), as labrig's retrieve.rs computes them, once as a pyarrow filter
      and once as DuckDB SQL: {"pyarrow": [source_path...], "duckdb": [source_path...],
      "sql": "...", "rows": n, "duckdb_by_format": {...}}
"""
import glob
import json
import math
import os
import sys

import duckdb
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq

CAMERAS = ["ext1", "ext2", "rs1", "rs2"]
KEY = "source_format"


def is_hive(index):
    return bool(glob.glob(os.path.join(index, f"{KEY}=*")))


def table(index):
    """The index's rows sorted by source_path, columns by name, the key as a plain string."""
    if is_hive(index):
        # What a user types; pyarrow infers the key from the folder names (as a dictionary).
        t = pq.read_table(index)
        assert ds.dataset(index, format="parquet", partitioning="hive").count_rows() == t.num_rows
        t = t.set_column(t.schema.get_field_index(KEY), KEY, pc.cast(t[KEY], pa.string()))
    else:
        t = ds.dataset(sorted(glob.glob(os.path.join(index, "part-*.parquet"))), format="parquet").to_table()
    return t.select(sorted(t.column_names)).sort_by([("source_path", "ascending")])


def duck_source(index):
    if is_hive(index):
        return f"read_parquet('{os.path.join(index, '*', '*.parquet')}', hive_partitioning = true)"
    return f"read_parquet('{os.path.join(index, 'part-*.parquet')}')"


def partitions_consistent(index):
    """Each file under source_format=<f>/ leaves the key to its folder (no such column)."""
    if not is_hive(index):
        return None
    for d in glob.glob(os.path.join(index, f"{KEY}=*")):
        for f in glob.glob(os.path.join(d, "*.parquet")):
            if KEY in pq.read_schema(f).names:
                return False
    return True


def plain(v):
    if isinstance(v, float) and math.isnan(v):
        return "NaN"
    return v


def compare(a, b):
    ta, tb = table(a), table(b)
    out = {
        "rows_a": ta.num_rows,
        "rows_b": tb.num_rows,
        "columns_a": [f"{f.name}:{f.type}" for f in ta.schema],
        "columns_b": [f"{f.name}:{f.type}" for f in tb.schema],
        "partitions_consistent": [partitions_consistent(a), partitions_consistent(b)],
    }
    diffs = []
    if out["columns_a"] != out["columns_b"]:
        diffs.append("the columns differ")
    if ta.num_rows != tb.num_rows:
        diffs.append(f"{ta.num_rows} rows against {tb.num_rows}")
    if not diffs:
        for name in ta.column_names:
            ca, cb = ta[name].to_pylist(), tb[name].to_pylist()
            for k, (x, y) in enumerate(zip(ca, cb)):
                # NaN == NaN here: the same unknown value on both sides.
                if x != y and not (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
                    diffs.append(f"row {k} ({ta['source_path'][k]}) column {name}: {plain(x)!r} != {plain(y)!r}")
                    break
    out["equal"] = not diffs
    out["differences"] = diffs[:10]
    return out


def query(index, q):
    t = table(index)
    xy, z = q["cam_xy"], q["cam_z"]
    keep = pa.array([True] * t.num_rows)
    for tx, ty, tz in q["cameras"]:
        near = None
        for c in CAMERAS:
            m = pc.and_(
                pc.and_(
                    pc.less_equal(pc.abs(pc.subtract(t[f"{c}_x"], tx)), xy),
                    pc.less_equal(pc.abs(pc.subtract(t[f"{c}_y"], ty)), xy),
                ),
                pc.less_equal(pc.abs(pc.subtract(t[f"{c}_z"], tz)), z),
            )
            m = pc.fill_null(m, False)
            near = m if near is None else pc.or_(near, m)
        keep = pc.and_(keep, near)
    (bx, by, bz), (hx, hy, hz) = q["box_centre"], [v / 2 for v in q["box"]]
    inside = pc.and_(
        pc.and_(
            pc.less_equal(pc.abs(pc.subtract(t["object_x"], bx)), hx),
            pc.less_equal(pc.abs(pc.subtract(t["object_y"], by)), hy),
        ),
        pc.less_equal(pc.abs(pc.subtract(t["object_z"], bz)), hz),
    )
    keep = pc.and_(keep, pc.fill_null(inside, False))
    py = sorted(t.filter(keep)["source_path"].to_pylist())

    cam_terms = []
    for tx, ty, tz in q["cameras"]:
        anyc = " OR ".join(
            f"(abs({c}_x - {tx!r}) <= {xy!r} AND abs({c}_y - {ty!r}) <= {xy!r} AND abs({c}_z - {tz!r}) <= {z!r})"
            for c in CAMERAS
        )
        cam_terms.append(f"coalesce({anyc}, false)")
    box = (
        f"abs(object_x - {bx!r}) <= {hx!r} AND abs(object_y - {by!r}) <= {hy!r} AND abs(object_z - {bz!r}) <= {hz!r}"
    )
    where = " AND ".join([*cam_terms, f"coalesce({box}, false)"])
    sql = f"SELECT source_path FROM {duck_source(index)} WHERE {where} ORDER BY source_path"
    con = duckdb.connect()
    dk = [r[0] for r in con.sql(sql).fetchall()]
    by_format = dict(con.sql(f"SELECT {KEY}, count(*) FROM {duck_source(index)} GROUP BY 1 ORDER BY 1").fetchall())
    return {"pyarrow": py, "duckdb": dk, "sql": sql, "rows": t.num_rows, "duckdb_by_format": by_format}


def main():
    mode = sys.argv[1]
    if mode == "compare":
        print(json.dumps(compare(sys.argv[2], sys.argv[3])))
    elif mode == "query":
        print(json.dumps(query(sys.argv[2], json.loads(sys.argv[3]))))
    else:
        sys.exit(f"unknown mode {mode}")


if __name__ == "__main__":
    main()
