# One command each for a new user (see README.md).
.PHONY: demo test lint

demo:  ## set up the environment and run the main job on the bundled demo scene
	bash scripts/demo.sh

test:  ## set up the environment and run the tests
	bash scripts/test.sh

lint:
	bash -c 'VENV=$$(bash scripts/setup_env.sh | tail -n 1) && $$VENV/bin/ruff check .'
