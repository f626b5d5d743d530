# The --figures options of the benchmark scripts that record their headline figures into a
# docs/figures file through `mac-ego3d bench record-figures` (as the bench commands' own --figures
# do), parsed in one place. Sourced:
#
#   source scripts/figure_options.sh
#   take_figure_options "$@" || exit 2
#   set -- "${figure_rest[@]}"        # the script's own options, parsed as before
#   ...
#   record_figures "$bin" FIGURES_INPUT_JSON "the script's command line"
#
# Options: --figures FILE --figures-section HEADING [--figures-label TEXT] [--machine TEXT].
figures=""
figures_section=""
figures_label=""
machine=""
figure_rest=()

take_figure_options() {
  figure_rest=()
  while (($#)); do
    case "$1" in
      --figures | --figures-section | --figures-label | --machine)
        (($# > 1)) || { echo "$1 needs a value" >&2; return 2; }
        case "$1" in
          --figures) figures="$2" ;;
          --figures-section) figures_section="$2" ;;
          --figures-label) figures_label="$2" ;;
          --machine) machine="$2" ;;
        esac
        shift 2 ;;
      *) figure_rest+=("$1"); shift ;;
    esac
  done
  if [[ -n "$figures" && -z "$figures_section" ]]; then
    echo "--figures needs --figures-section HEADING (the docs/benchmarks.md entry)" >&2
    return 2
  fi
}

# record_figures BIN INPUT COMMAND: writes INPUT's figures into --figures (nothing without it).
record_figures() {
  [[ -n "$figures" ]] || return 0
  "$1" bench record-figures --from "$2" --command "$3" --figures "$figures" \
    --figures-section "$figures_section" ${machine:+--machine "$machine"}
}
