# `make lerobot-env`: a separate virtual environment with huggingface's `lerobot` 0.4.4, for the test that
# loads `midas export --format lerobot` with LeRobot's own LeRobotDataset (tests/interop/test_lerobot.py; it skips
# without this environment unless MIDAS_REQUIRE_LEROBOT=1). Included from the Makefile; opt-in, not part of
# `make test`: lerobot pins torch < 2.11, opencv < 4.13 and packaging < 26, which clash with midas's pins,
# and its dataset module imports torchvision, whose PyPI wheels load only beside a CUDA build of torch, so
# this environment holds torch 2.14.1 + torchvision 0.29.1 with their CUDA libraries (about 6 GB; pip takes
# them from a local wheel cache where one is configured) and lerobot with --no-deps beside the pinned
# packages its dataset code imports (mk/lerobot-requirements.txt). Decoding the video feature needs the
# system's FFmpeg libraries (torchcodec loads them; .ci/run installs ffmpeg).
LEROBOT_VENV ?= .venv-lerobot
LEROBOT_STAMP := $(LEROBOT_VENV)/.installed

.PHONY: lerobot-env

$(LEROBOT_STAMP): mk/lerobot-requirements.txt
	$(PYTHON) -m venv $(LEROBOT_VENV)
	$(LEROBOT_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(LEROBOT_VENV)/bin/python -m pip install --quiet torch==2.14.1 torchvision==0.29.1
	$(LEROBOT_VENV)/bin/python -m pip install --quiet --no-deps -r mk/lerobot-requirements.txt
	$(LEROBOT_VENV)/bin/python -c "from lerobot.datasets.lerobot_dataset import LeRobotDataset"
	touch $(LEROBOT_STAMP)

lerobot-env: $(LEROBOT_STAMP)
