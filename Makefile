# The two commands a newcomer needs: `make run` (the main job) and `make test`.
# Both fetch MuJoCo 3.17's shared library from PyPI into third_party/ first, if it is missing.

MUJOCO := third_party/mujoco/libmujoco.so

.PHONY: run test lint bench mujoco

run: $(MUJOCO)
	cargo run --release -- sim hold

test: $(MUJOCO)
	cargo test --workspace

lint: $(MUJOCO)
	cargo fmt --check
	cargo clippy --workspace --all-targets -- -D warnings

bench: $(MUJOCO)
	cargo run --release -- bench sim

mujoco: $(MUJOCO)

$(MUJOCO):
	./scripts/fetch-mujoco.sh
