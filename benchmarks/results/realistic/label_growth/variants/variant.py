"""python /tmp/variant.py <sparseart cli args>; env GROW=off|id|noid"""
import os, sys
from dataclasses import replace
import sparseart.labelers.rules as rules
orig = rules.grow_parts
mode = os.environ.get("GROW", "id")
def patched(labels, s, e, cfg, rng):
    if mode == "off":
        return {}
    return orig(labels, s, e, replace(cfg, identity_excludes=("id" in mode), takes_unassigned=("static" not in mode), colour_gap=float(os.environ.get("CGAP", "0.06"))), rng)
rules.grow_parts = patched
from sparseart.cli import main
sys.exit(main(sys.argv[1:]))
