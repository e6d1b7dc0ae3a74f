package android.system;

public final class Os {
    public static int getuid() {
        throw new RuntimeException("Stub!");
    }

    public static void setuid(int uid) throws ErrnoException {
        throw new RuntimeException("Stub!");
    }
}
