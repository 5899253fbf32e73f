"""Security properties that a code change could quietly break: checked on the source itself."""

import ast
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("cscsr", "stages", "pipeline")


def sources():
    for package in PACKAGES:
        yield from sorted((ROOT / package).rglob("*.py"))


def calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            yield node


def name_of(call: ast.Call) -> str:
    f = call.func
    parts = []
    while isinstance(f, ast.Attribute):
        parts.append(f.attr)
        f = f.value
    if isinstance(f, ast.Name):
        parts.append(f.id)
    return ".".join(reversed(parts))


def test_weights_never_go_through_pickle():
    for path in sources():
        tree = ast.parse(path.read_text())
        for call in calls(tree):
            assert name_of(call) not in ("torch.load", "pickle.load", "pickle.loads", "np.load", "numpy.load"), \
                f"{path.relative_to(ROOT)}:{call.lineno}: {name_of(call)} can run pickled code"
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert "pickle" not in names, f"{path.relative_to(ROOT)}:{node.lineno} imports pickle"


def test_no_shell_command_is_built_from_strings():
    for path in sources():
        for call in calls(ast.parse(path.read_text())):
            name = name_of(call)
            assert name not in ("os.system", "os.popen", "subprocess.getoutput"), f"{path.relative_to(ROOT)}:{call.lineno}"
            shell = [k for k in call.keywords if k.arg == "shell"]
            assert not shell or (isinstance(shell[0].value, ast.Constant) and shell[0].value.value is False), \
                f"{path.relative_to(ROOT)}:{call.lineno}: shell=True"


def test_the_scheduler_is_published_on_loopback_only():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for name, service in compose["services"].items():
        for port in service.get("ports", []):
            text = port if isinstance(port, str) else f"{port.get('host_ip', '')}:{port.get('published')}"
            assert text.startswith("127.0.0.1:"), f"{name} publishes {port} beyond this machine"
    assert "TLS" in (ROOT / "docker-compose.yml").read_text() and "tls" in (ROOT / "docs" / "cluster.md").read_text()
