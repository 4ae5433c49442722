#!/usr/bin/env bash
# headforge batch track over the two shared clips plus one corrupt file: on a local Ray runtime,
# its re-run (the finished items skipped), and one after another in-process, into WORK (the first
# argument; wiped). The clips are symlinked, never copied. Figures: docs/batch_and_distributed.md.
#   flock /tmp/headforge-heavy.lock benchmarks/batch_track_ray.sh /tmp/hf45
set -u
WORK=${1:?usage: batch_track_ray.sh WORK_FOLDER}
VIDEO=$(cd "$(dirname "$0")/../.." && pwd)/shared/data/video
mkdir -p "$WORK" && cd "$WORK" || exit 1
rm -rf clips ray_out seq_out
mkdir clips
ln -s "$VIDEO/talking_bun.mp4" clips/talking_bun.mp4
ln -s "$VIDEO/talking_longhair.mp4" clips/talking_longhair.mp4
head -c 200000 /dev/urandom > clips/corrupt.mp4
OPTS="--max-frames 60 --resolution 256 --no-overlay --cpus-per-item 1"
export OMP_NUM_THREADS=1
echo "== ray $(date -u +%T)"; /usr/bin/time -f "wall %e s" nice -n 10 headforge batch track clips -o ray_out --ray --ray-cpus 2 $OPTS; echo "rc=$?"
echo "== ray rerun $(date -u +%T)"; /usr/bin/time -f "wall %e s" nice -n 10 headforge batch track clips -o ray_out --ray --ray-cpus 2 $OPTS; echo "rc=$?"
echo "== sequential $(date -u +%T)"; /usr/bin/time -f "wall %e s" nice -n 10 headforge batch track clips -o seq_out $OPTS; echo "rc=$?"
echo "== done $(date -u +%T)"; cat ray_out/summary.md seq_out/summary.md; uptime
