# vbench.sh SRC_OUT NAME GROW settings... : rerun a cached bench folder's scenes with a variant
src=$1; name=$2; mode=$3; shift 3
out=/tmp/v/$name; mkdir -p $out; ln -sfn $src/scenes $out/scenes
objs=$(python -c "
import csv; print(' '.join(sorted({'/work/shared/data/partnet/'+r['object'] if not r['object'].endswith('_multi') or r['object'].startswith('oven') else '/work/shared/data/partnet-twins/'+r['object'] for r in csv.DictReader(open('$src/rows.csv'))})))")
seeds=$(python -c "
import json; print(' '.join(sorted({str(r.get('seed',0)) for r in json.load(open('$src/rows.json'))})))" 2>/dev/null)
cd /work/main && GROW=$mode python /tmp/variant.py bench --objects $objs --settings "$@" --seeds ${SEEDS:-0} --no-peer --out $out > $out.log 2>&1
