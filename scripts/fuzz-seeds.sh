#!/bin/sh
# Makes the fuzz seeds in fuzz/corpus/<target>/ with flowmimic's
# own commands on the smallest settings (fuzz/seeds.toml over the tiny preset). The BVH and
# DeepMimic seeds are hand-written and committed as they are.
set -eu
cd "$(dirname "$0")/.."
cargo build --release --quiet
fm="target/release/flowmimic --preset tiny --config fuzz/seeds.toml"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# Quiet unless a step fails.
step() { "$@" >"$work/log" 2>&1 || { cat "$work/log"; exit 1; }; }
step $fm motion generate --duration 0.5 --name walk -o "$work/clips"
step $fm track train --clip "$work/clips/walk.clip.safetensors" -o "$work/expert"
step $fm collect "$work/expert" -o "$work/data"
step $fm train "$work/data" -o "$work/model"
step $fm run --model "$work/model" --task walk --seconds 0.2 --clip "$work/clips/walk.clip.safetensors" \
    -o "$work/walk.rollout.safetensors"
shard=$(ls "$work/data"/*.rollouts.safetensors)
for t in clip policy model stats rollout shard manifest config; do rm -rf "fuzz/corpus/$t"; mkdir -p "fuzz/corpus/$t"; done
cp "$work/clips/walk.clip.safetensors" fuzz/corpus/clip/
cp "$work/expert/policy.safetensors" fuzz/corpus/policy/
cp "$work/model/model.safetensors" fuzz/corpus/model/
cp "$work/model/stats.safetensors" fuzz/corpus/stats/
cp "$work/walk.rollout.safetensors" fuzz/corpus/rollout/
cp "$shard" fuzz/corpus/shard/
cp "$work/data/manifest.json" fuzz/corpus/manifest/
cp configs/*.toml fuzz/corpus/config/
du -sh fuzz/corpus/*
