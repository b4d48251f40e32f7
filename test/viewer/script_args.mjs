// What every script here starts with: its `--name value` arguments, and a require() that loads the npm tools of
// deploy/install_deploy_tools.sh (--tools DIR, else $CVISLAM_DEPLOY_TOOLS, else out/deploy-tools of this checkout),
// which live outside the repository.
import { createRequire } from "node:module";
import path from "node:path";

export function scriptArgs() {
  const args = {};
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i++) {
    if (argv[i].startsWith("--")) args[argv[i].slice(2)] = argv[i + 1];
  }
  const tools = args.tools ?? process.env.CVISLAM_DEPLOY_TOOLS ?? path.resolve(import.meta.dirname, "../../out/deploy-tools");
  return { args, tools, require: createRequire(path.join(tools, "node_modules", "x.js")) };
}
