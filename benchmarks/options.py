"""Command-line options shared by the suites that train, calibrate and score one tree (``inspection``, ``real``)."""


def add_align_options(parser):
    """``--align`` / ``--no-align`` on a suite's parser (``args.align``: True, False or None, the inspection's own
    choice: registered when the training scans' poses spread), for :func:`calibrate_and_score`'s ``align``."""
    align = parser.add_mutually_exclusive_group()
    align.add_argument("--align", dest="align", action="store_const", const=True, default=None,
                       help="calibrate and score with --align (every scan registered onto the training scans first)")
    align.add_argument("--no-align", dest="align", action="store_const", const=False,
                       help="with --no-align (default: the inspection's own choice, registered when the training "
                            "scans' poses spread)")


def add_calibration_options(parser, cache_help, work, folds_help=""):
    """The options of a suite that trains, calibrates and scores one tree (``inspection``, ``real``): ``--folds``
    (:func:`fold_settings`), ``--point-scores`` (:func:`parse_point_scores`), ``--cache`` (``cache_help`` says what
    it holds), ``--work`` (default ``work``) and ``--progress``. ``folds_help``: what ``both`` adds, if anything."""
    from benchmarks import cache

    parser.add_argument("--folds", choices=("on", "off", "both"), default="off",
                        help="calibrate without fold models (off: the default, the held-back scans' level and the "
                             "training scans cross-fitted), with 2 fold models trained into the cached model (on: "
                             "train_latent.py --calibration-folds 2), or both" + folds_help)
    parser.add_argument("--point-scores", default=None, metavar="LIST",
                        help="also each of these point scores alone (NAME[:AGGREGATE],...; no ray score, one "
                             "calibration each), a row each: the ablation suite's --trees")
    parser.add_argument("--cache", default=cache.CACHE, help=f"{cache_help} (default: %(default)s)")
    parser.add_argument("--work", default=work, help="scored runs (default: %(default)s)")
    parser.add_argument("--progress", action="store_true", help="progress bars")


def fold_settings(choice):
    """The calibrations ``--folds`` asks for (``'on'``, ``'off'`` or ``'both'``): with the fold models (True),
    without (False), in that order."""
    return {"on": (True,), "off": (False,), "both": (False, True)}[choice]
