#!/bin/sh
# Open3D needs the system library libusb-1.0. Install it when missing and we can (root
# with apt-get); otherwise print the exact command and stop.
set -e
if ldconfig -p 2>/dev/null | grep -q 'libusb-1\.0\.so\.0'; then
  exit 0
fi
for d in /lib /usr/lib /lib/x86_64-linux-gnu /usr/lib/x86_64-linux-gnu /lib/aarch64-linux-gnu /usr/lib/aarch64-linux-gnu; do
  [ -e "$d/libusb-1.0.so.0" ] && exit 0
done
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "libusb-1.0 missing (Open3D needs it): installing libusb-1.0-0 with apt-get"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0
  exit 0
fi
echo "Open3D needs the system library libusb-1.0, which is not installed. Run:" >&2
echo "    sudo apt-get install libusb-1.0-0" >&2
exit 1
