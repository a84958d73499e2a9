# The two commands a newcomer needs: `make run` (the main job) and `make test`.
# Both fetch MuJoCo 3.17's shared library from PyPI into third_party/ first, if it is missing.

MUJOCO := third_party/mujoco/libmujoco.so
# numpy and onnxruntime for the ONNX export check (optional: skipped when they cannot be installed).
PYDEPS := third_party/python

.PHONY: run demo test lint bench mujoco chromium python

# The whole pipeline on the cpu preset: the walking corpus -> one PPO policy -> rollouts -> the FM
# guidance model and its inverse dynamics -> evaluation (about an hour on 2 cores).
run: $(MUJOCO)
	cargo run --release -- pipeline

# Minutes instead of an hour: the shipped models walk on a joystick and reach.
demo: $(MUJOCO)
	cargo run --release -- demo
	cargo run --release -- render runs/demo/joystick.rollout.safetensors -o runs/demo/joystick.gif
	cargo run --release -- render runs/demo/reach.rollout.safetensors -o runs/demo/reach.gif

test: $(MUJOCO) $(PYDEPS) chromium
	cargo test --workspace
	./scripts/test-python.sh

# The Python package into the current Python environment (Rust and pip needed; a few minutes).
python:
	python3 -m pip install ./python

lint: $(MUJOCO)
	cargo fmt --check
	cargo clippy --workspace --all-targets -- -D warnings

bench: $(MUJOCO)
	cargo run --release -- bench sim
	cargo run --release -- bench model

mujoco: $(MUJOCO)

$(MUJOCO):
	./scripts/fetch-mujoco.sh

$(PYDEPS):
	./scripts/fetch-pydeps.sh

# Headless Chromium for the browser tests (optional: skipped with a message without it).
chromium:
	./scripts/fetch-chromium.sh
