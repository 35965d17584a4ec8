# The two Quick-start commands; each does its own set-up (scripts/bootstrap.sh).
.PHONY: demo test bootstrap

bootstrap:
	@scripts/bootstrap.sh

demo: bootstrap
	.venv/bin/walkstream demo

test: bootstrap
	.venv/bin/python -m pytest -q
