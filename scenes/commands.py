"""`nerfgauge scenes`: list the scenes, one line each."""

from nerfgauge.scenes.registry import list_scenes

def register(subparsers) -> None:
    parser = subparsers.add_parser("scenes", help="list the procedural scenes")
    parser.set_defaults(func=run)


def run(args) -> int:
    rows = list_scenes()
    width = max(len(name) for name, _ in rows)
    for name, text in rows:
        print(f"{name:<{width}}  {text}")
    return 0
