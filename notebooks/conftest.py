"""pytest options for running the chapters under nbval (`make test`).

nbval 0.11 waits a fixed 5 s for each output message of a cell once the kernel has replied. On a
busy machine the kernel can be slower than that to publish them: the cell then fails with
"Timeout of 5 seconds exceeded waiting for output", nbval stops the kernel, and every later cell
of the notebook fails with it. nbval has no option for that wait, so this file adds one.
"""

OUTPUT_TIMEOUT_S = 120.0  # generous: a cell that finished only waits for messages already sent


def pytest_addoption(parser):
    parser.addoption(
        "--nbval-output-timeout",
        type=float,
        default=OUTPUT_TIMEOUT_S,
        help="seconds nbval waits for each output message of a cell that has run "
        f"(nbval's own: 5; here: {OUTPUT_TIMEOUT_S:g})",
    )


def pytest_collection_modifyitems(config, items):
    timeout = config.getoption("nbval_output_timeout")
    for item in items:
        if hasattr(item, "output_timeout"):  # an nbval cell
            item.output_timeout = timeout
