"""Run usd-core's validators (pxr.UsdValidation) on USD files; exit 1 if any reports an error.

Usage: python scripts/usd_check.py [--json REPORT] file.usda [file.usdz ...]
Prints one JSON object per file: {"file", "errors", "warnings", "messages": [...]}.
Also fails on files that do not open, and on layers missing upAxis / metersPerUnit /
defaultPrim (the validators only warn about some of these).
"""
import argparse
import json
import sys

from pxr import Sdf, Usd, UsdGeom, UsdValidation


def check(path, ctx):
    out = {"file": path, "errors": 0, "warnings": 0, "messages": []}
    try:
        stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    except Exception as e:  # noqa: BLE001 - report any open failure
        out["errors"] += 1
        out["messages"].append({"type": "Error", "name": "open", "message": str(e)})
        return out
    for err in ctx.Validate(stage):
        kind = str(err.GetType()).split(".")[-1]
        msg = {"type": kind, "name": str(err.GetName()), "message": err.GetMessage()}
        out["messages"].append(msg)
        if err.GetType() == UsdValidation.ValidationErrorType.Error:
            out["errors"] += 1
        elif err.GetType() == UsdValidation.ValidationErrorType.Warn:
            out["warnings"] += 1
    for key, ok in (
        ("upAxis", stage.HasAuthoredMetadata("upAxis")),
        ("metersPerUnit", stage.HasAuthoredMetadata("metersPerUnit")),
        ("defaultPrim", stage.GetDefaultPrim().IsValid()),
    ):
        if not ok:
            out["errors"] += 1
            out["messages"].append({"type": "Error", "name": "pii-bake:" + key, "message": key + " is not authored"})
    if stage.HasAuthoredMetadata("metersPerUnit") and UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
        out["messages"].append({"type": "Warn", "name": "pii-bake:metersPerUnit", "message": "metersPerUnit is not 1"})
        out["warnings"] += 1
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", help="write all reports to this file")
    ap.add_argument("files", nargs="+")
    args = ap.parse_args()
    reg = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext(reg.GetOrLoadAllValidators())
    reports = [check(f, ctx) for f in args.files]
    for r in reports:
        print(json.dumps(r))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(reports, fh, indent=2)
    sys.exit(1 if any(r["errors"] for r in reports) else 0)


if __name__ == "__main__":
    main()
