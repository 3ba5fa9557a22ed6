#!/usr/bin/env bash
# What a session lent an H100/H200 for about ten minutes runs at once, in order:
#
#   1. the environment check: devices, package versions, the deterministic-ops flag;
#   2. Chapter 3's Point-Maze at `paper` (bench/ch3_pointmaze_paper.py: five seeds side by
#      side, sized by its loops' first iterations at the thesis's shapes: QD-PG and TD3,
#      and the other methods while they fit POINTMAZE_S, 330 s), unless
#      data/published/paper/ch3_pointmaze/ holds it: commit the JSON it writes there, the
#      Chapter 3 page shows it as a published run;
#   3. the primer at `paper`, published as an archive, unless data/published holds it
#      (run on an H100 on 2026-12-05: 84 s, committed);
#   4. the dry run at `paper` (python -m qdnb dryrun) of each notebook no GPU dry run in
#      bench/results/*_dryrun_gpu*.json has finished (DRYRUN_NOTEBOOKS overrides), one step
#      of at most DRYRUN_STEP_S (240) seconds each;
#   5. bench/scale_out.py --real: every stage's rate on the GPU's own devices;
#   6. the dry runs' report rebuilt from their records: a notebook a step's limit stopped
#      is reported "cut off", with the loops it reached (their GPU rates count).
#
# Everything it writes goes under one folder, OUT (the first argument, else $OUT, else
# bench/results/gpu_session/): log.txt, environment.json, pointmaze-paper.json (copy it to
# data/published/paper/ch3_pointmaze/), the published archive,
# scale_out_gpu.json, paper_dryrun_gpu.json (copy it to bench/results/ under a name ending
# _dryrun_gpu.json; the CPU dry run's report then gets its GPU hours with
# python -m qdnb dryrun all --report-only).  SESSION_S (520) bounds steps 1-5 (the device
# call's 600 s, less the machine's start and step 5): each step's timeout is cut to what is
# left.  A step that fails is logged and the next one still runs.
#
# The GPU machines cannot reach a package registry.  Their image has JAX (CUDA), flax,
# optax, orbax, pandas and matplotlib; the rest of requirements.lock travels as wheels:
#
#   bench/gpu_session.sh --prepare      # here, with network: downloads them into .whl/
#
# then run it there with .whl carried (device `run`: carry [".whl"]):
#
#   bash bench/gpu_session.sh "$OUT"
set -u
cd "$(dirname "$0")/.."

# the image's own packages (../.library/device/KINDS.md, 2026-11-17): not carried
IMAGE_HAS="absl-py chex flax jax jaxlib ml-dtypes numpy opt-einsum optax orbax-checkpoint
pandas matplotlib scipy tqdm pyyaml jinja2 markupsafe packaging pillow pygments typing-extensions
etils msgpack protobuf tensorstore toolz treescope rich humanize nest-asyncio fsspec attrs
python-dateutil six pyparsing kiwisolver cycler fonttools contourpy tzdata pytz simplejson
psutil requests urllib3 idna certifi charset-normalizer click zipp wheel setuptools pip
filelock aiofiles"

# what only the book's rendering, JupyterLab or the tests need: not carried (64 MiB a call)
BOOK_ONLY="jupyter-book pydata-sphinx-theme accessible-pygments alabaster babel docutils
imagesize snowballstemmer pybtex pybtex-docutils latexcodec django-static-mathjax sqlalchemy
jupyter-cache jupyter-builder notebook notebook-shim selenium pysocks outcome wsproto
sortedcontainers ruff nbmake flask flask-cors itsdangerous werkzeug blinker terminado
send2trash jupyter-lsp jupyter-events argon2-cffi argon2-cffi-bindings async-lru json5
linkify-it-py uc-micro-py websockets websocket-client uvloop mujoco-studio pyopengl glfw
tensorboardx"

if [ "${1:-}" = "--prepare" ]; then
    rm -rf .whl
    mkdir -p .whl
    grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo "/.whl/" >> .git/info/exclude
    # every pinned package the image lacks, as CPython 3.12 manylinux wheels, no dependencies
    grep -E '^[A-Za-z0-9_.-]+==' requirements.lock | sed 's/ .*//' | while read -r pin; do
        name=$(echo "${pin%%==*}" | tr 'A-Z_' 'a-z-')
        case " $(echo $IMAGE_HAS) " in *" $name "*) continue ;; esac
        case " $(echo $BOOK_ONLY) " in *" $name "*) continue ;; esac
        case "$name" in sphinx*|myst-*|jupyterlab*|jupyter-server*|trio*|pytest*) continue ;; esac
        python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
            --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
            --platform manylinux2014_x86_64 --platform any -d .whl "$pin" \
            || echo "no wheel for $pin (install it there another way)"
    done
    du -sh .whl
    exit 0
fi

OUT=${1:-${OUT:-bench/results/gpu_session}}
mkdir -p "$OUT"
LOG="$OUT/log.txt"
export PYTHONUNBUFFERED=1
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}  # qdnb itself, for bench/ and the kernels
PY=${PY:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}

SESSION_S=${SESSION_S:-520}  # the whole session's seconds: no step runs past them

step() {  # step NAME SECONDS COMMAND...: run, time and log one step; never stop the session
    local name=$1 limit=$2
    shift 2
    local left=$((SESSION_S - SECONDS))
    [ "$left" -lt "$limit" ] && limit=$left
    if [ "$limit" -le 10 ]; then
        echo "── $name: skipped, the session's $SESSION_S s are spent" | tee -a "$LOG"
        return
    fi
    echo "── $(date -u +%H:%M:%S) $name (at most $limit s)" | tee -a "$LOG"
    local began=$SECONDS
    timeout "$limit" "$@" >>"$LOG" 2>&1
    local rc=$?
    echo "── $name: exit $rc after $((SECONDS - began)) s" | tee -a "$LOG"
}

step "environment" 120 "$PY" - "$OUT/environment.json" <<'EOF'
import json, os, sys
import jax
from qdnb.book import provenance
from qdnb.book.provenance import DETERMINISTIC_FLAG
info = {
    "devices": [str(d) for d in jax.devices()],
    "device": provenance.device_text(),
    "versions": provenance.versions(),
    "xla_flags": os.environ.get("XLA_FLAGS", ""),
    "deterministic_flag_set": DETERMINISTIC_FLAG in os.environ.get("XLA_FLAGS", ""),
    "deterministic_flag": DETERMINISTIC_FLAG,
}
print(json.dumps(info, indent=1))
json.dump(info, open(sys.argv[1], "w"), indent=1)
EOF

POINTMAZE=data/published/paper/ch3_pointmaze/pointmaze-paper.json  # committed once run
if [ -e "$POINTMAZE" ]; then
    echo "── Point-Maze at paper is already published ($POINTMAZE): not run again" | tee -a "$LOG"
else
    # its budget: POINTMAZE_S less the sizing's own time; the step's limit leaves it 60 s more
    step "ch3 Point-Maze at paper" $((${POINTMAZE_S:-330} + 60)) "$PY" \
        bench/ch3_pointmaze_paper.py --budget-s "${POINTMAZE_S:-330}" --out "$OUT/pointmaze-paper.json"
fi

ARCHIVE="$OUT/paper-ch2_primer.tar.gz"
KEPT=data/published/paper/ch2_primer/ch2_primer-paper.tar.gz  # a session's run, committed
if [ -e "$ARCHIVE" ] || [ -e "$KEPT" ]; then
    echo "── the primer at paper is already published ($KEPT): not run again" | tee -a "$LOG"
else
    step "ch2_primer at paper" 300 "$PY" -m qdnb run ch2_primer --scale paper
    step "publish ch2_primer" 60 "$PY" -m qdnb publish paper ch2_primer --out "$ARCHIVE"
fi
# the dry runs not yet made on a GPU (bench/results/*_dryrun_gpu*.json), one step each: a
# notebook the step's limit cuts off still leaves its loops' records, gathered at the end
NOTEBOOKS=${DRYRUN_NOTEBOOKS:-$("$PY" - <<'EOF'
import json
from pathlib import Path
from qdnb.book.runner import notebook_names
done = set()
for path in Path("bench/results").glob("*_dryrun_gpu*.json"):
    nbs = json.loads(path.read_text()).get("notebooks", {})
    done |= {n for n, nb in nbs.items() if nb.get("status") == "ok"}
print(" ".join(n for n in notebook_names() if n not in done and n != "ch2_primer"))
EOF
)}
REPORT="$OUT/paper_dryrun_gpu.json"
for nb in $NOTEBOOKS; do
    step "dry run of $nb" "${DRYRUN_STEP_S:-240}" "$PY" -m qdnb dryrun "$nb" --scale paper \
        --out "$REPORT"
done
step "scale_out --real" 150 "$PY" bench/scale_out.py --real --out "$OUT/scale_out_gpu.json"
# kept out of SESSION_S: what the cut-off dry runs reached, from their records
echo "── the dry runs' report, from their records" | tee -a "$LOG"
timeout 40 "$PY" -m qdnb dryrun $NOTEBOOKS --scale paper --report-only --out "$REPORT" \
    >>"$LOG" 2>&1
echo "── done: $OUT" | tee -a "$LOG"
