# Sourced by the scripts that start the binaries themselves (not through cargo): the lavapipe
# scripts/setup.sh provisions on Debian 12 (target/vulkan/icd.json) is added beside the
# system's Vulkan drivers, as cargo adds it (.cargo/config.toml). A VK_ADD_DRIVER_FILES already
# set wins. render-core then prefers a GPU, else the newest lavapipe;
# MAC_EGO3D_ADAPTER picks another (e.g. MAC_EGO3D_ADAPTER="Mesa 22").
mac_ego3d_icd="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/target/vulkan/icd.json"
if [[ -z "${VK_ADD_DRIVER_FILES+set}" && -f "$mac_ego3d_icd" ]]; then
  export VK_ADD_DRIVER_FILES="$mac_ego3d_icd"
fi
unset mac_ego3d_icd
